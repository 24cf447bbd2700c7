"""pytest plugin: run a hil configuration from a test and assert latency budgets.

Installed with the package as the ``hil`` ``pytest11`` entry point, so any test in
an environment where ``hil-harness`` is installed can ask for the ``hil_run``
fixture (elsewhere: ``pytest -p hil.harness.cli.pytest_plugin``)::

    def test_my_ai_budget(hil_run):
        result = hil_run("hil_configs/regression.yaml", overrides=["duration_s=5"])
        result.assert_budget(vehicle="ego0", stage="end_to_end", p99_ms=80)
        result.assert_no_drops()

``hil_run(config, *, overrides=(), require_complete=True)`` runs the config (a YAML
path, relative to the working directory, else to pytest's rootdir, else to the
checkout holding the package's ``hil_configs/``; or a mapping)
in a fresh folder under the test's ``tmp_path`` and returns a :class:`HilRunResult`
(``.summary`` as written, ``.figures`` typed: :class:`hil.harness.vocab.figures.RunFigures`,
``.run_dir``, ``.mcap_path``). A config mistake or a target that
cannot start fails the test with the one-line error, no traceback; a run that
ended early (its target died) fails it unless ``require_complete=False``.

For CI: every run's figures become properties of the test (``hil.N.ego0.end_to_end.p99_ms``,
``hil.N.verdict.failed``, ``hil.N.run_dir`` ...; N counts the test's runs from 1), which
pytest writes into ``--junitxml``; ``--hil-keep-runs DIR`` copies each run folder to
``DIR/<test id>/hil-N-<config>/`` (the test's ``tmp_path`` is not kept), to archive as
CI artifacts; ``hil.N.run_dir`` then names the copy.

Loading this module is cheap: MuJoCo and the harness are imported on the first run,
after the GL backend is chosen (``hil.scenarios.gl.select_backend``).
"""

from __future__ import annotations

import functools
import os
import re
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from hil.harness.vocab.figures import RunFigures, StageFigures

_BUDGET_KEYS = ("p50_ms", "p90_ms", "p99_ms", "max_ms", "mean_ms", "std_ms")


@dataclass(frozen=True)
class HilRunResult:
    """A finished run: its folder and parsed ``summary.json`` (``summary``, as
    written; ``figures``: typed, what the assertions read)."""

    run_dir: Path
    summary: dict[str, Any]

    @property
    def mcap_path(self) -> Path:
        return self.run_dir / "run.mcap"

    @functools.cached_property
    def figures(self) -> RunFigures:
        """The summary as :class:`hil.harness.vocab.figures.RunFigures`.

        Raises:
            hil.common.errors.ConfigError: a malformed field, named.
        """
        from hil.harness.vocab.figures import RunFigures

        return RunFigures.from_json(self.summary)

    def _vehicles(self, vehicle: str | None) -> list[str]:
        known = list(self.figures.vehicles)
        if vehicle is None:
            return known
        if vehicle not in known:
            raise AssertionError(f"no vehicle {vehicle!r} in the run (vehicles: {', '.join(known) or 'none'}); "
                                 f"run folder {self.run_dir}")
        return [vehicle]

    def latency(self, vehicle: str, stage: str = "end_to_end") -> dict[str, Any]:
        """The summary figures of one stage (``count``, ``p50_ms`` ... ``std_ms``).

        Raises:
            AssertionError: no such vehicle or stage, or no samples.
        """
        __tracebackhide__ = True
        return self._stage(vehicle, stage).to_json()

    def _stage(self, vehicle: str, stage: str) -> StageFigures:
        __tracebackhide__ = True
        (v,) = self._vehicles(vehicle)
        stages = self.figures.vehicles[v].latency_ms
        st = stages.get(stage)
        if st is None or not st.count:
            raise AssertionError(f"no latency samples for {v} {stage} (stages with samples: "
                                 f"{', '.join(k for k, s in stages.items() if s.count) or 'none'}); "
                                 f"run folder {self.run_dir}")
        return st

    def assert_budget(self, *, vehicle: str | None = None, stage: str = "end_to_end",
                      p50_ms: float | None = None, p90_ms: float | None = None, p99_ms: float | None = None,
                      max_ms: float | None = None, mean_ms: float | None = None,
                      std_ms: float | None = None) -> None:
        """Assert that ``stage`` of ``vehicle`` (default: every vehicle) stays within
        each budget given (ms). Every violation is listed in one message.

        Raises:
            AssertionError: what, measured, budget, by how much; and the run folder.
        """
        __tracebackhide__ = True  # pytest shows the user's line, not this one
        budgets = {k: v for k, v in zip(_BUDGET_KEYS, (p50_ms, p90_ms, p99_ms, max_ms, mean_ms, std_ms))
                   if v is not None}
        if not budgets:
            raise TypeError("assert_budget needs at least one budget, e.g. p99_ms=80")
        over = []
        for v in self._vehicles(vehicle):
            st = self._stage(v, stage)
            for key, budget in budgets.items():
                measured = st.figure(key)
                if measured is not None and measured > budget:
                    pct = f"{(measured / budget - 1) * 100:+.1f} %, " if budget > 0 else ""
                    over.append(f"  {v} {stage} {key[:-3]} = {measured:.3f} ms > budget {budget:.3f} ms "
                                f"(over by {measured - budget:.3f} ms, {pct}{st.count} frames)")
        if over:
            raise AssertionError("latency budget exceeded:\n" + "\n".join(over)
                                 + f"\nrun folder: {self.run_dir} (see report.html / run.mcap)")

    def assert_drop_rate(self, max_rate: float, *, vehicle: str | None = None) -> None:
        """Assert that each vehicle's drop rate (dropped / frames) is at most ``max_rate``.

        Raises:
            AssertionError: which vehicle, its drops and rate, the limit.
        """
        __tracebackhide__ = True
        over = []
        for v in self._vehicles(vehicle):
            s = self.figures.vehicles[v]
            rate = 0.0 if s.drop_rate is None else float(s.drop_rate)
            if rate > max_rate:
                over.append(f"  {v}: {s.dropped} of {s.frames_sent} frames dropped "
                            f"(rate {rate:.4f} > {max_rate:.4f})")
        if over:
            raise AssertionError("dropped frames:\n" + "\n".join(over) + f"\nrun folder: {self.run_dir}")

    def assert_no_drops(self, *, vehicle: str | None = None) -> None:
        """Assert that no frame was dropped (no estimate within the timeout)."""
        __tracebackhide__ = True
        self.assert_drop_rate(0.0, vehicle=vehicle)


def config_search_path(rootdir: Path | None) -> list[Path]:
    """Where a relative config path is looked for, in order: the working directory,
    pytest's rootdir, and the folder holding this package's ``hil_configs/`` (a
    checkout or an editable install), so ``hil_configs/regression.yaml`` works from
    any test session."""
    package_root = Path(__file__).resolve().parents[2]  # harness/ sits next to hil_configs/
    places = [Path.cwd(), *([rootdir] if rootdir is not None else []), package_root]
    return list(dict.fromkeys(p.resolve() for p in places))


def _resolve(config: str | os.PathLike[str], rootdir: Path | None) -> Path:
    """The config file ``config`` names (see ``config_search_path``).

    Raises:
        hil.common.errors.ConfigError: found in none of the places (all are listed).
    """
    from hil.common.errors import ConfigError

    p = Path(config)
    if p.is_absolute():
        return p
    places = config_search_path(rootdir)
    for base in places:
        if (base / p).is_file():
            return base / p
    raise ConfigError(f"config file not found: {p} (looked in {', '.join(str(b) for b in places)})")


def run_config(config: str | os.PathLike[str] | Mapping[str, Any], *, out_dir: Path,
               overrides: Sequence[str] = (), require_complete: bool = True,
               rootdir: Path | None = None) -> HilRunResult:
    """Run ``config`` into the new folder ``out_dir`` (what the fixture calls).

    Raises:
        hil.common.errors.HilError: a config mistake, a target that cannot start.
        AssertionError: the run ended early and ``require_complete`` is set.
    """
    result = _run(config, out_dir=out_dir, overrides=overrides, rootdir=rootdir)
    _check_complete(result, require_complete)
    return result


def _check_complete(result: HilRunResult, require_complete: bool) -> None:
    ended = result.figures.ended_by
    if require_complete and ended != "duration":
        raise AssertionError(f"hil run ended early: {ended}; run folder {result.run_dir}")


def _run(config: str | os.PathLike[str] | Mapping[str, Any], *, out_dir: Path, overrides: Sequence[str],
         rootdir: Path | None) -> HilRunResult:
    from hil.scenarios.gl import select_backend

    backend = select_backend()  # before anything imports mujoco
    from hil.harness.config.loading import load_config, parse_config
    from hil.harness.run.driver import execute, prepare_out_dir

    overrides = ["progress=false", *overrides]
    if isinstance(config, Mapping):
        cfg = parse_config(config, overrides=overrides)
    else:
        cfg = load_config(_resolve(config, rootdir), overrides=overrides)
    from hil.harness.record.out_dir import release_out_dir

    try:
        result = execute(cfg, out_dir=prepare_out_dir(out_dir), gl_backend=backend, install_signal_handlers=False)
    finally:
        release_out_dir(out_dir)  # a test session runs many runs: give each folder's claim back
    if not (result.out_dir / "report.html").exists():  # hil.harness.run.driver may write it already
        from hil.harness.report.run_report import write_report

        write_report(result.out_dir)
    return HilRunResult(result.out_dir, result.summary)


def run_properties(result: HilRunResult, prefix: str) -> list[tuple[str, object]]:
    """A run's figures as test properties (names under ``prefix``): its folder, how
    it ended, the verdict and ``hil.harness.report.ci_cases.run_figures``."""
    from hil.harness.report.ci_cases import run_figures

    v = result.figures.verdict
    props: dict[str, object] = {"run_dir": str(result.run_dir), "ended_by": result.figures.ended_by,
                                "verdict.passed": v.passed, "verdict.failed": ",".join(v.failed),
                                **run_figures(result.figures)}
    return [(f"{prefix}.{k}", "" if x is None else x) for k, x in props.items()]


def keep_run(run_dir: Path, keep_dir: Path, test_id: str) -> Path:
    """Copy ``run_dir`` to ``keep_dir/<test_id as a folder name>/<its name>`` (an
    earlier copy of the same test's run is replaced); returns the copy."""
    dest = keep_dir / re.sub(r"[^A-Za-z0-9_.-]+", "_", test_id).strip("_") / run_dir.name
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(run_dir, dest, ignore=shutil.ignore_patterns(".hil-run.lock"))
    return dest


class HilRunner:
    """The ``hil_run`` fixture's value: call it to run a config (see module docstring)."""

    def __init__(self, base_dir: Path, *, rootdir: Path | None = None,
                 record: Callable[[tuple[str, object]], None] | None = None, keep_dir: Path | None = None,
                 test_id: str = "test") -> None:
        self._base = base_dir
        self._rootdir = rootdir
        self._count = 0
        self._record, self._keep_dir, self._test_id = record, keep_dir, test_id

    def __call__(self, config: str | os.PathLike[str] | Mapping[str, Any], *, overrides: Sequence[str] = (),
                 require_complete: bool = True) -> HilRunResult:
        from hil.common.errors import HilError

        self._count += 1
        name = "config" if isinstance(config, Mapping) else Path(config).stem
        out = self._base / f"hil-{self._count}-{name}"
        try:
            result = _run(config, out_dir=out, overrides=overrides, rootdir=self._rootdir)
        except HilError as err:
            pytest.fail(f"hil_run: {err}", pytrace=False)
        if self._keep_dir is not None:
            result = HilRunResult(keep_run(result.run_dir, self._keep_dir, self._test_id), result.summary)
        if self._record is not None:  # before any assertion: a failed test keeps its figures too
            for prop in run_properties(result, f"hil.{self._count}"):
                self._record(prop)
        try:
            _check_complete(result, require_complete)
        except AssertionError as err:
            pytest.fail(str(err), pytrace=False)
        return result


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.getgroup("hil").addoption(
        "--hil-keep-runs", dest="hil_keep_runs", default=None, metavar="DIR",
        help="copy every hil_run run folder to DIR/<test id>/ (CI artifacts); the test's properties name the copy")


@pytest.fixture
def hil_run(tmp_path: Path, request: pytest.FixtureRequest) -> HilRunner:
    """Run a hil configuration in ``tmp_path`` and get its summary back:
    ``hil_run("hil_configs/regression.yaml", overrides=["duration_s=5"])``. Each
    run's figures become the test's properties (``--junitxml``); ``--hil-keep-runs
    DIR`` keeps its folder."""
    keep = request.config.getoption("hil_keep_runs", default=None)
    keep_dir = None if keep is None else Path(keep).resolve()
    # record_property's list (without its warning under junit_family xunit2, which writes them all the same).
    return HilRunner(tmp_path, rootdir=Path(request.config.rootpath), record=request.node.user_properties.append,
                     keep_dir=keep_dir, test_id=request.node.nodeid)


__all__ = ["HilRunResult", "HilRunner", "config_search_path", "hil_run", "keep_run", "pytest_addoption", "run_config",
           "run_properties"]

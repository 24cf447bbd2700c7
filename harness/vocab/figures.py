"""``summary.json`` as the run's typed figures: :class:`RunFigures`, what the report,
the pytest plugin, the run-folder reader, the CLI and the CI outputs read (attribute
access, no string keys).

``hil.harness.run.summary`` writes the file (schema in README.md, ``schema_version``
1); this is its reading side. :meth:`RunFigures.from_json` takes every
``summary.json`` the harness ever wrote: a key a summary lacks (an older run, kept as
a baseline) gets its field's documented default (in each record's docstring; never a
made-up measurement: ``None`` where a figure is unknown, 0 or ``{}`` for counts), and
``verdict`` is rebuilt from the figures for a run made before it existed. A value of
the wrong type is one :class:`hil.common.errors.ConfigError` line naming the field
(``vehicles.ego0.dropped: expected an integer, got 'x'``); the run-folder loader puts
the file in front of it, and the CLI exits 2.

Typed: what readers take by key. Kept as written, in each record's ``extra``: the
sections no reader takes apart (top level: ``scenario_realized``, ``latency_profile``,
``session``, ``impairment``, ``can_log``, ``spill``, ``rosbag2``, ``target_batches``,
``recorder_error``; ``realtime.lateness_histogram``; per vehicle: ``streaming_ms``,
``splits_ms``, ``splits_excluded``; see :mod:`hil.harness.vocab.figures_vehicle`).
Mappings keep the file's order (vehicles, stages, checks).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from hil.common.errors import ConfigError
from hil.harness.vocab.figures_json import Fields, field_names, optional
from hil.harness.vocab.figures_vehicle import (ClockFigures, LinkFigures, Outcome, RigCamera, RigFigures,
                                               StageBudget, StageFigures, TargetHello, VehicleFigures)


@dataclass(frozen=True)
class CameraHealth:
    """``realtime.camera``: frames handed to the links, those later than
    ``tolerance_ms`` after their camera instant, the worst lag (ms), late frames by
    vehicle."""

    frames: int = 0
    late_frames: int = 0
    tolerance_ms: float | None = None
    worst_lag_ms: float | None = None
    by_vehicle: Mapping[str, int] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> CameraHealth:
        return cls(f.integer("frames"), f.integer("late_frames"), f.opt_number("tolerance_ms"),
                   f.opt_number("worst_lag_ms"), f.counts("by_vehicle"))


@dataclass(frozen=True)
class RealtimeFigures:
    """``realtime`` (README): whether the run kept real time and why not. Missing in
    an older summary: numbers ``None``, counts 0, ``camera`` ``None``, ``kept_realtime``
    true exactly when nothing is ``lagging``. ``extra``: ``lateness_histogram`` and
    anything newer, as written."""

    mode: str = "unknown"
    requested_factor: float | None = None
    achieved_factor: float | None = None
    run_factor: float | None = None
    late_steps: int = 0
    late_tolerance_ms: float | None = None
    steps_over_10ms: int = 0
    lateness_ms: Mapping[str, float | None] = field(default_factory=dict)
    max_lateness_ms: float | None = None
    camera: CameraHealth | None = None
    behind: Mapping[str, int] = field(default_factory=dict)
    lagging: tuple[str, ...] = ()
    kept_realtime: bool = True
    physics_scheduling: str | None = None
    render_workers: int | None = None
    shards: int | None = None
    renderer: str | None = None
    render_warm_ms: float | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> RealtimeFigures:
        cam = f.obj("camera")
        lagging = f.texts("lagging")
        return cls(f.text("mode", "unknown"), f.opt_number("requested_factor"), f.opt_number("achieved_factor"),
                   f.opt_number("run_factor"), f.integer("late_steps"), f.opt_number("late_tolerance_ms"),
                   f.integer("steps_over_10ms"), f.nums("lateness_ms"), f.opt_number("max_lateness_ms"),
                   None if cam is None else CameraHealth.from_json(cam), f.counts("behind"), lagging,
                   f.flag("kept_realtime", not lagging), f.opt_text("physics_scheduling"),
                   f.opt_integer("render_workers"), f.opt_integer("shards"), f.opt_text("renderer"),
                   f.opt_number("render_warm_ms"), f.rest(field_names(cls)))


@dataclass(frozen=True)
class CheckFigures:
    """One check of the verdict (``hil.harness.vocab.verdict.Check`` as written):
    ``name`` is a ``CheckName`` value, kept as text (a summary may hold a check this
    build does not know)."""

    name: str
    ok: bool
    headline: str
    measured: float | None = None
    limit: float | None = None
    unit: str = ""
    details: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> CheckFigures:
        return cls(f.text("name"), f.flag("ok", True), f.text("headline"), f.opt_number("measured"),
                   f.opt_number("limit"), f.text("unit"), f.raw_obj("details") or {})

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "ok": self.ok, "headline": self.headline, "measured": self.measured,
                "limit": self.limit, "unit": self.unit, "details": dict(self.details)}


@dataclass(frozen=True)
class VerdictFigures:
    """``verdict``: ``passed``, the checks that ``failed``, ``fail_on``, those failed
    and named there (``fails_run``), the ``limits`` and every check."""

    passed: bool
    failed: tuple[str, ...]
    fail_on: tuple[str, ...]
    fails_run: tuple[str, ...]
    limits: Mapping[str, float | None]
    checks: tuple[CheckFigures, ...]

    @classmethod
    def from_json(cls, f: Fields) -> VerdictFigures:
        checks = f.items("checks")
        return cls(f.flag("passed", True), f.texts("failed"), f.texts("fail_on"), f.texts("fails_run"),
                   f.nums("limits"),
                   tuple(CheckFigures.from_json(Fields(c, f"{f.at('checks')}[{i}]")) for i, c in enumerate(checks)))

    def check(self, name: str) -> CheckFigures | None:
        """The check called ``name``, if the verdict has it."""
        return next((c for c in self.checks if c.name == name), None)

    @property
    def headline(self) -> str:
        """The verdict in one line, as the terminal and the report open with it: the
        failed checks, and whether any of them fails the run (``--fail-on``): a run
        whose failed checks are only warnings still ends with exit 0."""
        if self.passed:
            return "all checks passed"
        n = len(self.failed)
        text = f"{n} check{'s' if n != 1 else ''} failed: {', '.join(self.failed)}"
        if not self.fails_run:
            return f"{text} (warnings only: none is in --fail-on, so the run does not fail on them)"
        return f"{text}; the run fails on {', '.join(self.fails_run)} (--fail-on)"

    def to_json(self) -> dict[str, Any]:
        """As ``hil.harness.vocab.verdict.verdict_json`` writes it."""
        return {"passed": self.passed, "failed": list(self.failed), "fail_on": list(self.fail_on),
                "fails_run": list(self.fails_run), "limits": dict(self.limits),
                "checks": [c.to_json() for c in self.checks]}


@dataclass(frozen=True)
class HarnessCost:
    """``harness_cost``: the harness's own CPU per frame (µs) and its start and finish
    (s); ``None`` where an older summary has no such figure."""

    frames: int | None = None
    run_us_per_frame: float | None = None
    loop_thread_us_per_frame: float | None = None
    analysis_thread_us_per_frame: float | None = None
    analysis_tasks_dropped: int | None = None
    start_s: float | None = None
    finish_s: float | None = None
    windows_s: float | None = None
    summary_s: float | None = None
    threads_us_per_frame: dict[str, float | None] = field(default_factory=dict)  # the run process's, by role

    @classmethod
    def from_json(cls, f: Fields) -> HarnessCost:
        return cls(frames=f.opt_integer("frames"), run_us_per_frame=f.opt_number("run_us_per_frame"),
                   loop_thread_us_per_frame=f.opt_number("loop_thread_us_per_frame"),
                   analysis_thread_us_per_frame=f.opt_number("analysis_thread_us_per_frame"),
                   analysis_tasks_dropped=f.opt_integer("analysis_tasks_dropped"), start_s=f.opt_number("start_s"),
                   finish_s=f.opt_number("finish_s"), windows_s=f.opt_number("windows_s"),
                   summary_s=f.opt_number("summary_s"), threads_us_per_frame=f.nums("threads_us_per_frame"))


@dataclass(frozen=True)
class RecorderFigures:
    """``recorder``: MCAP messages ``written`` (``derived`` of them: the Foxglove
    views), ``enqueued``, ``dropped``, ``bytes_written``; ``None`` where an older
    harness did not count it. ``extra``: other counters, as written."""

    written: int | None = None
    derived: int | None = None
    enqueued: int | None = None
    dropped: int | None = None
    bytes_written: int | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> RecorderFigures:
        return cls(written=f.opt_integer("written"), derived=f.opt_integer("derived"),
                   enqueued=f.opt_integer("enqueued"), dropped=f.opt_integer("dropped"),
                   bytes_written=f.opt_integer("bytes_written"), extra=f.rest(field_names(cls)))


@dataclass(frozen=True)
class CornerCases:
    """``corner_cases``: cases ``written``, ``errors`` writing them, triggers dropped."""

    written: int = 0
    errors: tuple[str, ...] = ()
    triggers_dropped: int = 0

    @classmethod
    def from_json(cls, f: Fields) -> CornerCases:
        return cls(f.integer("written"), f.texts("errors"), f.integer("triggers_dropped"))


@dataclass(frozen=True)
class RunEvents:
    """``events``: every event ``published``, those ``unrecorded`` (queue full), and
    by kind those of no vehicle (``run``)."""

    published: int = 0
    unrecorded: int = 0
    run: Mapping[str, int] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> RunEvents:
        return cls(f.integer("published"), f.integer("unrecorded"), f.counts("run"))


@dataclass(frozen=True)
class RunFigures:
    """A run's ``summary.json`` (README), typed. What ran (``name`` ... ``versions``:
    ``None`` when not written), how it ended (``ended_by``; ``None``: not written), the
    durations (s), real-time health, the verdict (always there: rebuilt from the
    figures for a summary without one), the harness's cost, collisions (as written:
    ``sim_time_ns``, ``a``, ``b``, ``striker``, ...), events, recorder, corner cases and
    every vehicle (the file's order). ``extra``: the other top-level sections, as
    written (see the module docstring)."""

    vehicles: Mapping[str, VehicleFigures]
    verdict: VerdictFigures
    schema_version: int = 1
    name: str | None = None
    scenario: str | None = None
    scenario_params: Mapping[str, Any] | None = None
    seed: int | None = None
    config_hash: str | None = None
    gl_backend: str | None = None
    versions: Mapping[str, Any] | None = None
    ended_by: str | None = None
    sim_time_s: float | None = None
    wall_time_s: float | None = None
    realtime: RealtimeFigures | None = None
    harness_cost: HarnessCost | None = None
    collisions: tuple[Mapping[str, Any], ...] = ()
    events: RunEvents | None = None
    recorder: RecorderFigures | None = None
    corner_cases: CornerCases | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, d: Any) -> RunFigures:
        """The figures of a parsed ``summary.json`` (any the harness wrote).

        Raises:
            ConfigError: not an object, no ``vehicles`` object, or a field of the wrong
                type; one line naming the field by its dotted path.
        """
        from hil.harness.vocab.verdict import verdict_json

        f = Fields(d)
        if f.obj("vehicles") is None:
            raise ConfigError("vehicles: missing (JSON without a 'vehicles' mapping)")
        collisions = f.items("collisions")
        for i, c in enumerate(collisions):
            Fields(c, f"collisions[{i}]")
        # Every figure checked before a verdict is rebuilt from them.
        vehicles = {name: VehicleFigures.from_json(v) for name, v in f.objs("vehicles").items()}
        realtime, cases = optional(RealtimeFigures, f.obj("realtime")), optional(CornerCases, f.obj("corner_cases"))
        verdict = f.obj("verdict")
        if verdict is None or "checks" not in verdict.d:
            verdict = Fields(verdict_json(f.d), "verdict")
        return cls(
            vehicles=vehicles, verdict=VerdictFigures.from_json(verdict), schema_version=f.integer("schema_version", 1),
            name=f.opt_text("name"), scenario=f.opt_text("scenario"), scenario_params=f.raw_obj("scenario_params"),
            seed=f.opt_integer("seed"), config_hash=f.opt_text("config_hash"), gl_backend=f.opt_text("gl_backend"),
            versions=f.raw_obj("versions"), ended_by=f.opt_text("ended_by"), sim_time_s=f.opt_number("sim_time_s"),
            wall_time_s=f.opt_number("wall_time_s"), realtime=realtime,
            harness_cost=optional(HarnessCost, f.obj("harness_cost")), collisions=collisions,
            events=optional(RunEvents, f.obj("events")), recorder=optional(RecorderFigures, f.obj("recorder")),
            corner_cases=cases, extra=f.rest(field_names(cls)))

    @property
    def completed(self) -> bool:
        """The run ran its whole duration (``ended_by`` is ``duration``)."""
        return self.ended_by == "duration"


__all__ = ["CameraHealth", "CheckFigures", "ClockFigures", "CornerCases", "HarnessCost", "LinkFigures", "Outcome",
           "RealtimeFigures", "RecorderFigures", "RigCamera", "RigFigures", "RunEvents", "RunFigures", "StageBudget",
           "StageFigures", "TargetHello", "VehicleFigures", "VerdictFigures"]

"""The ``hil`` command line.

Exit codes: 0 success; 1 the run ended early (target died, interrupted) or part of
its outputs could not be written (a corner case); 2 a user mistake (bad config,
missing file, target that cannot start) with a one-line message and no traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.common.errors import ConfigError, HilError
from hil.harness.cli.parser import EXIT_EARLY, EXIT_OK, EXIT_USAGE, TARGETS, build_parser, live_before_config

if TYPE_CHECKING:
    from hil.harness.vocab.figures import RunFigures

# Commands whose module has add_parser(sub) and cmd(args), by name.
COMMANDS = {"report": "hil.harness.report.run_report", "compare": "hil.harness.check.gate",
            "train": "hil.training.train", "calibrate": "hil.harness.check.calibrate",
            "study": "hil.harness.study.study", "trace": "hil.harness.report.trace",
            "rosbag": "hil.harness.report.rosbag2"}


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except BrokenPipeError:
        # The reader of the output left (``hil scenarios --json | head``): no traceback,
        # and none from Python flushing stdout at exit either.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_EARLY


def _renders(argv: list[str]) -> bool:
    """Whether ``hil ARGV`` renders (so selects a GL backend): ``run``, ``calibrate``,
    ``replay``, ``search`` (not its merge, cases or report); not for help."""
    if not argv or argv[0] not in ("run", "calibrate", "replay", "search") or "-h" in argv or "--help" in argv:
        return False
    from hil.harness.search.cli import SUBCOMMANDS

    return not (argv[0] == "search" and argv[1:2] and argv[1] in SUBCOMMANDS)


def _main(argv: Sequence[str] | None) -> int:
    if argv is None:  # the program (not a caller in its own process): SIGUSR2 prints its stacks
        from hil.harness.engine.procs import stacks_on_sigusr2

        stacks_on_sigusr2()
    argv = list(sys.argv[1:] if argv is None else argv)
    if not _renders(argv):
        return _command(argv)
    from hil.scenarios.gl import cancel_probe, start_probe

    start_probe()  # the GL probe (MUJOCO_GL unset) runs while the command loads what it needs
    try:
        return _command(argv)
    finally:
        cancel_probe()


def _command(argv: list[str]) -> int:
    if len(argv) >= 2 and argv[0] == "target" and argv[1] in TARGETS:
        # Everything after the name belongs to the target (including --help).
        import importlib

        target_argv = argv[2:]
        if "--once" not in target_argv and "--keep-serving" not in target_argv:
            target_argv = ["--keep-serving", *target_argv]  # a target on a bench serves run after run
        return int(importlib.import_module(TARGETS[argv[1]]).main(target_argv, prog=f"hil target {argv[1]}") or 0)
    if argv[:1] == ["target"] and (len(argv) == 1 or argv[1] in ("-h", "--help")):
        print(_target_help(), end="", file=sys.stdout if len(argv) > 1 else sys.stderr)
        return EXIT_OK if len(argv) > 1 else EXIT_USAGE
    if argv and argv[0] == "search":
        # hil search SPEC ... / hil search merge|cases|report ...: parsed by hil.harness.search.cli.
        from hil.harness.search import cli as search_cli

        return search_cli.main(argv[1:])
    args = build_parser(argv[0] if argv else None).parse_args(live_before_config(argv))
    try:
        if args.command == "run":
            return _cmd_run(args)
        if args.command in ("cases", "replay"):
            from hil.harness.cli import cases as cases_cmd

            return cases_cmd.cmd_cases(args) if args.command == "cases" else cases_cmd.cmd_replay(args)
        if args.command == "clock":
            from hil.harness.cli import clock as clock_cmd

            return clock_cmd.cmd(args)
        if args.command == "scenarios":
            return _cmd_scenarios(args)
        if args.command == "target-check":
            from hil.harness.check import target_check

            return target_check.cmd(args)
        if args.command in COMMANDS:
            import importlib

            return int(importlib.import_module(COMMANDS[args.command]).cmd(args))
    except HilError as err:
        print(f"hil: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("hil: interrupted before the run started; nothing recorded", file=sys.stderr)
        return EXIT_EARLY
    return EXIT_USAGE  # pragma: no cover - argparse requires a command


# One line per example target for ``hil target --help``.
_TARGET_SUMMARIES = {
    "cnn": "the paper's two-CNN AI in torch (detector + steering net, baseline fallback)",
    "cv": "the classical OpenCV baseline (colour-blob detection, pinhole ranging, lane keeping)",
    "echo": "a fixed answer after a set busy time: the transport and timing floor",
}


def _target_help() -> str:
    from hil.adapters.sdk import TRANSPORTS

    names, transports = "|".join(sorted(TARGETS)), "|".join(TRANSPORTS)
    lines = [f"usage: hil target {{{names}}} [--transport {transports}] [options of the target]", "",
             "Serve an example AI target over a transport, e.g. on a remote host or device:",
             "  hil target cv --transport zenoh --listen tcp/0.0.0.0:7447",
             "  hil target cv --transport tcp --listen 0.0.0.0:7600", "",
             "It serves run after run until Ctrl-C/SIGTERM (--once: one run).", "",
             "targets:"]
    lines += [f"  {name:<6} {_TARGET_SUMMARIES.get(name, '')}" for name in sorted(TARGETS)]
    lines += ["", "Each target's own options: hil target NAME --help (e.g. hil target cv --help)."]
    return "\n".join(lines) + "\n"


def run_exit_code(summary: dict[str, object]) -> int:
    """``hil run``'s exit code for a finished run: 1 when it ended early or a corner
    case could not be written (``summary["corner_cases"]["errors"]``), 3 when a verdict
    named by ``--fail-on`` / ``verdict.fail_on`` failed, else 0."""
    cases = summary.get("corner_cases")
    if summary.get("ended_by") != "duration":
        return EXIT_EARLY
    if isinstance(cases, dict) and cases.get("errors"):
        return EXIT_EARLY
    verdict = summary.get("verdict")
    if isinstance(verdict, dict) and verdict.get("fails_run"):
        from hil.harness.vocab.verdict import EXIT_VERDICT

        return EXIT_VERDICT
    return EXIT_OK


def realtime_warning(realtime: dict[str, Any], *, sim_steps: int) -> str | None:
    """What was not kept when a real-time run fell behind (the physics, the cameras or
    both, as ``realtime.lagging`` says), and what to do; None when it kept real time
    (or ran in lockstep)."""
    if realtime.get("kept_realtime", True):
        return None
    lagging = realtime.get("lagging") or ["physics"]
    parts = []
    if "physics" in lagging:
        achieved, requested = float(realtime["achieved_factor"]), float(realtime["requested_factor"])
        late, tol = int(realtime["late_steps"]), float(realtime.get("late_tolerance_ms", 10.0))
        worst = float(realtime.get("max_lateness_ms", 0.0))
        if achieved < 0.95 * requested:
            parts.append(f"the physics ran at {achieved:.2f}x wall-clock speed where {requested:g}x was asked "
                         f"({late} of {sim_steps} steps more than {tol:g} ms late, worst {worst:.1f} ms)")
        else:
            parts.append(f"{late} of {sim_steps} physics steps ran more than {tol:g} ms late "
                         f"(worst {worst:.1f} ms), though the physics as a whole kept pace ({achieved:.2f}x)")
    if "camera" in lagging:
        cam = realtime.get("camera") or {}
        parts.append(f"the camera pipeline lagged: {cam.get('late_frames')} of {cam.get('frames')} frames left "
                     f"more than {cam.get('tolerance_ms'):g} ms after their camera instant "
                     f"(worst {cam.get('worst_lag_ms'):.1f} ms)")
    if "consumers" in lagging:
        behind = realtime.get("behind") or {}
        parts.append("the harness fell behind the physics, which did not wait: records lost by "
                     + ", ".join(f"{name} ({n})" for name, n in sorted(behind.items())))
    return (f"real time was not kept: {'; '.join(parts)}; latencies were measured on a late simulation. "
            f"Close other programs, lower camera.fps, the image size or the number of vehicles, or use "
            f"mode: lockstep")


def _cmd_scenarios(args: argparse.Namespace) -> int:
    import json

    from hil.scenarios import catalog

    if args.json:
        print(json.dumps(catalog.as_dict(args.name), indent=2))
    else:
        print(catalog.describe(args.name), end="")
    return EXIT_OK


def _cmd_run(args: argparse.Namespace) -> int:
    from hil.harness.engine.procs import start_child_server, stop_child_server

    start_child_server()  # MUJOCO_GL chosen by the user: the engine's modules load meanwhile too
    try:
        return _run(args)
    finally:
        stop_child_server()


def _run(args: argparse.Namespace) -> int:
    from hil.harness.cli.progress import Progress, final_table
    from hil.harness.report.progress import make_console
    from hil.harness.config.loading import load_config
    from hil.harness.report.ci_outputs import check_ci_args, write_ci_outputs
    from hil.harness.config.model import Mode
    from hil.harness.engine.procs import physics_core, start_child_server
    from hil.harness.run.driver import default_out_dir, execute, prepare_out_dir
    from hil.scenarios.gl import select_backend

    check_ci_args(args)  # --junit / --json writable: checked before anything runs
    overrides = list(args.overrides)
    if args.live is not None:  # --live, or --live HOST:PORT (a JSON string: "[::1]:8765" is no YAML list)
        overrides.append("recording.live=true")
        if args.live:
            overrides.append(f"recording.live_address={json.dumps(args.live)}")
    cfg = load_config(args.config, overrides=overrides)
    if args.fail_on:
        from hil.harness.vocab.verdict import parse_fail_on

        try:
            names = parse_fail_on(args.fail_on)
        except ValueError as err:
            raise ConfigError(f"--fail-on: {err}") from err
        fail_on = list(dict.fromkeys([*cfg.verdict.fail_on, *(n.value for n in names)]))
        cfg = cfg.model_copy(update={"verdict": cfg.verdict.model_copy(update={"fail_on": fail_on})})
    from hil import scenarios  # validate scenario and parameters before starting anything

    try:
        scenarios.get(cfg.scenario.name).resolve(cfg.scenario.params)
    except ConfigError as err:
        raise ConfigError(f"{err}{_scenario_switch_hint(args.overrides, str(err))}") from err
    if cfg.target.zenoh.auth is not None:
        cfg.target.zenoh.auth.usrpwd()  # the password's environment variable is set: checked before anything
    if cfg.mode == Mode.REALTIME:
        physics_core(cfg.engine.physics_cpu)  # a core this machine has: checked before anything
    out = prepare_out_dir(args.out or default_out_dir(cfg))
    console = make_console()
    backend = select_backend()
    start_child_server()  # where the GL probe chose: its imports overlap what follows (idempotent)
    console.print(f"renderer: MuJoCo offscreen via [bold]{backend.upper()}[/bold]"
                  + (" (software fallback: slower)" if backend == "osmesa" else ""))
    try:
        with Progress(console=console, enabled=cfg.progress and not args.no_progress) as progress:
            shown = progress.update if progress.enabled else None  # no table: no rows computed
            result = execute(cfg, out_dir=out, gl_backend=backend, on_progress=shown, notify=console.print)
    except (HilError, KeyboardInterrupt) as err:
        reason = mark_failed(out, err)
        if isinstance(err, KeyboardInterrupt) and (out / "run.mcap").is_file():
            print(f"hil: {reason}", file=sys.stderr)  # not main's "before the run started"
            return EXIT_EARLY
        raise
    s = result.summary
    from hil.harness.vocab.figures import RunFigures

    figures = RunFigures.from_json(s)
    print_verdict(console, figures)
    console.print(final_table(s))
    warning = realtime_warning(s["realtime"], sim_steps=round(s["sim_time_s"] / cfg.physics_step_s))
    if warning is not None:
        console.print(f"[yellow]warning: {warning}[/yellow]", markup=True, highlight=False)
    from rich.markup import escape

    for line in link_warnings(figures, rig_cameras=len(cfg.camera.cameras())):
        console.print(f"[yellow]warning: {escape(line)}[/yellow]", markup=True, highlight=False)
    console.print(f"run.mcap:     {result.mcap_path}")
    console.print(f"summary.json: {result.summary_path}")
    console.print(f"report.html:  {result.out_dir / 'report.html'}")
    if s["ended_by"] != "duration":
        console.print(f"[red]run ended early: {s['ended_by']}[/red] (what was recorded is kept)")
    errors = (s.get("corner_cases") or {}).get("errors") or []
    if errors:
        console.print(f"[red]{len(errors)} corner case(s) could not be written[/red] "
                      f"(summary.json corner_cases.errors): {errors[0]}", highlight=False)
    code = run_exit_code(s)
    from hil.harness.report.ci_cases import of_run

    write_ci_outputs(of_run(figures, run_dir=result.out_dir, exit_code=code), args)
    return code


def link_warnings(figures: RunFigures, *, rig_cameras: int = 1) -> list[str]:
    """What a user should know of each vehicle's link, one line each, from
    ``summary.json``: connections refused that were not its target
    (``vehicles.<name>.link.connections_refused``, ``refused``: a squatter on the port
    or a rogue dialling in was kept out), messages from the target that could not be
    decoded, estimates for frames already settled or never sent (none is a timing
    anomaly, so the verdict's lines do not show them), and a rig of ``rig_cameras``
    cameras whose target takes one camera, so it got camera 0 only
    (``events.rig_camera_zero_only``)."""
    out = []
    for name, v in figures.vehicles.items():
        for n, one, more, field in (
                (v.protocol_errors, "message from its target could not be decoded",
                 "messages from its target could not be decoded", "protocol_errors"),
                (v.unknown_estimates, "estimate for a frame never sent", "estimates for frames never sent",
                 "unknown_estimates"),
                (v.late_estimates, "estimate for a frame already settled (dropped, stale or answered before)",
                 "estimates for frames already settled (dropped, stale or answered before)", "late_estimates")):
            if n:
                out.append(f"{name}: {n} {one if n == 1 else more} (summary.json vehicles.{name}.{field}; "
                           "the events on /events)")
        n = v.link.connections_refused
        if n:
            named = "; ".join(v.link.refused)
            out.append(f"{name}: {n} connection{'s' * (n > 1)} refused, not the run's target"
                       + (f" ({named})" if named else "") + f" (summary.json vehicles.{name}.link.refused)")
        if v.events.get("rig_camera_zero_only"):
            out.append(f"{name}: its target did not announce CAP_CAMERAS, so it got camera 0 only of the "
                       f"{rig_cameras}-camera rig, as a single camera (PROTOCOL.md 4.2.1)")
    return out


def print_verdict(console: Any, figures: RunFigures) -> None:
    """The verdict first: a banner for a collision, then one line per check (met or
    missed, with its figures); the checks that fail the run (``--fail-on``) say so."""
    from rich.markup import escape

    v = figures.verdict
    col = v.check("collision")
    if col is not None and not col.ok:
        console.print(f"[bold white on red] COLLISION [/bold white on red] [bold red]{escape(col.headline)}"
                      "[/bold red]")
    fails = set(v.fails_run)
    console.print(f"[bold]verdict:[/bold] {escape(v.headline)}")
    for c in v.checks:
        mark = "[green]ok  [/green]" if c.ok else ("[bold red]FAIL[/bold red]" if c.name in fails
                                                    else "[yellow]warn[/yellow]")
        console.print(f"  {mark} {c.name:<9} {escape(c.headline)}", highlight=False)
    if fails:
        console.print(f"[bold red]the run fails on: {', '.join(sorted(fails))} (--fail-on): exit 3[/bold red]")


def mark_failed(out: Path, err: BaseException) -> str:
    """Say in the run folder ``out`` that its run never produced a summary, and why
    (``OUT/FAILED``), so a half-made folder is never taken for a run; returns the
    reason. An interruption says whether the recording had begun (``run.mcap``)."""
    reason = str(err)
    if isinstance(err, KeyboardInterrupt):
        mcap = out / "run.mcap"
        reason = "interrupted before the run started"
        if mcap.is_file():
            reason = (f"interrupted after the recording began, before the summary was written: {mcap} "
                      f"({mcap.stat().st_size:,} bytes) keeps what reached the disk (hil report {out} reads it)")
    if (out / "summary.json").exists():
        return reason
    try:
        from hil.harness.record.out_dir import FAILED_NAME

        (out / FAILED_NAME).write_text(f"this run did not start or did not finish: {reason}\n")
    except OSError:
        pass  # the folder itself is the problem; the error line says so
    return reason


def _scenario_switch_hint(overrides: Sequence[str], message: str) -> str:
    """A hint when ``--set scenario.name=X`` kept the config's parameters of another scenario."""
    switched = [o.partition("=")[2].strip() for o in overrides if o.replace(" ", "").startswith("scenario.name=")]
    if not switched or "unknown parameter" not in message:
        return ""
    name = switched[-1]
    return (f" (the config's scenario.params belong to its own scenario: add --set 'scenario.params={{}}', "
            f"or pick the scenario with its parameters: --set 'scenario={{name: {name}, params: {{}}}}')")


if __name__ == "__main__":
    raise SystemExit(main())

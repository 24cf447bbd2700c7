"""``hil calibrate [CONFIG]``: the harness proves its own accuracy on this machine
and link before it measures an AI.

It runs a short real-time run (the configured transport and endpoint) against the
reference target (``targets/reference.py``), which stamps on a clock with a known
offset and skew, spins a known inference time and injects spikes, a drop, a reorder,
a clock step and malformed messages, writing the truth of every frame to a file.
Then it prints, for every figure the run reports (clock offset and skew, inference,
transport, uplink and downlink splits, receipt lag, each anomaly), the error against
the truth and whether it lies inside the bound the harness stated, plus the
harness's own measuring overhead; and writes it all to ``calibration.json``.

Exit codes: 0 every figure inside its bound and every injected fault flagged exactly
once (and nothing flagged that the truth does not show); 1 otherwise; 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hil.common.errors import ConfigError
from hil.harness.check.calibrate_checks import Check, RunData, clock_checks, duration_checks, load_truth, overhead
from hil.harness.check.calibrate_faults import Cause, FaultCheck, Other, fault_checks, kind_table
from hil.harness.config.loading import dump_config, load_config, parse_config
from hil.harness.config.model import RunConfig, Transport

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "hil_configs" / "calibrate.yaml"
TRUTH_FILE = "reference_truth.jsonl"
REFERENCE_MODULE = "hil.targets.reference"


@dataclass
class Calibration:
    """The verdict: figure checks, fault checks, notes on other anomalies, overhead."""

    transport: str
    checks: list[Check] = field(default_factory=list)
    faults: list[FaultCheck] = field(default_factory=list)
    others: list[Other] = field(default_factory=list)
    overhead: dict[str, Any] = field(default_factory=dict)
    run_ok: bool = True
    run_note: str = ""

    @property
    def others_explained(self) -> bool:
        """No anomaly that the truth does not show (no false alarm, nothing flagged twice)."""
        return all(o.cause is not Cause.FALSE for o in self.others)

    @property
    def passed(self) -> bool:
        return (self.run_ok and self.others_explained and all(c.ok for c in self.checks)
                and all(f.ok for f in self.faults))

    def to_json(self) -> dict[str, Any]:
        return {"passed": self.passed, "transport": self.transport, "run_ok": self.run_ok,
                "run_note": self.run_note, "checks": [asdict(c) for c in self.checks],
                "faults": [asdict(f) for f in self.faults],
                "other_anomalies": [{**asdict(o), "cause": o.cause.value} for o in self.others],
                "anomaly_kinds": kind_table(self.faults, self.others),
                "others_explained": self.others_explained, "overhead": self.overhead}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def calibration_config(cfg: RunConfig, *, truth_path: Path, transport: Transport | None = None) -> RunConfig:
    """``cfg`` with the reference target as its target, writing ``truth_path``; over
    ``transport`` if given (Zenoh: on loopback, on a free port).

    Raises:
        ConfigError: the config's target is not the reference target, or a transport
            the reference target does not serve (it must run on this machine).
    """
    data = dump_config(cfg)
    tgt = data["target"]
    if transport is not None and transport.value != tgt["transport"]:
        tgt["transport"] = transport.value
        if transport == Transport.ZENOH:
            tgt["zenoh"]["base_port"] = _free_port()
            tgt["zenoh"]["connect"] = ["tcp/127.0.0.1:{port}"]
            tgt["zenoh"]["listen"] = []
    kind = tgt["transport"]
    if kind not in (Transport.LOCAL.value, Transport.ZENOH.value):
        raise ConfigError(f"target.transport: calibrate serves local or zenoh, got {kind!r}")
    if REFERENCE_MODULE not in tgt["command"]:
        raise ConfigError(f"target.command: calibrate runs the reference target ({REFERENCE_MODULE}), "
                          f"got {tgt['command']!r}")
    args = list(tgt["args"]) + ["--truth", str(truth_path)]
    given = tgt["command"] + args
    if kind == Transport.ZENOH.value and "--transport" not in given:
        # The reference target meets the harness at the configured endpoint: it listens
        # where the harness connects (or connects where the harness listens).
        z = tgt["zenoh"]
        side = ["--connect", z["listen"][0]] if z["listen"] else ["--listen", (z["connect"] or ["tcp/127.0.0.1:{port}"])[0]]
        # No --key-prefix: the harness hands a target it starts the run's keys in
        # HIL_ZENOH_KEY_PREFIX (per-run keys, so no other target can answer).
        args += ["--transport", "zenoh", *side, "--vehicle", "{vehicle_id}"]
    tgt["args"] = args
    data["progress"] = False
    return parse_config(data, source="calibrate")


def read_run(out_dir: Path, vehicle: str) -> tuple[RunData, int]:
    """The run's summary of ``vehicle`` and its MCAP topics; and the clock-sync count."""
    from mcap.reader import make_reader

    summary = json.loads((out_dir / "summary.json").read_text(encoding="utf-8"))
    topics: dict[str, list[dict[str, Any]]] = {}
    wanted = ["/events", f"/{vehicle}/pipeline", f"/{vehicle}/clock", f"/{vehicle}/clock_sync"]
    with open(out_dir / "run.mcap", "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages(topics=wanted, log_time_order=True):
            topics.setdefault(channel.topic, []).append(json.loads(message.data))
    events = [e for e in topics.get("/events", []) if e.get("vehicle") in (None, vehicle)]
    config = json.loads((out_dir / "config.json").read_text(encoding="utf-8"))
    max_delay_ms = float(((config.get("timing") or {}).get("sync") or {}).get("max_delay_ms", 50.0))
    run = RunData(summary["vehicles"][vehicle], topics.get(f"/{vehicle}/pipeline", []),
                  topics.get(f"/{vehicle}/clock", []), events, topics.get(f"/{vehicle}/clock_sync", []),
                  sync_max_delay_ns=int(max_delay_ms * 1e6))
    return run, len(run.sync)


def evaluate(out_dir: Path, *, transport: str, vehicle: str = "ego0") -> Calibration:
    """Check a finished calibration run folder against its truth file.

    Raises:
        ConfigError: the folder lacks the run or the truth file, or they are malformed.
    """
    truth = load_truth(out_dir / TRUTH_FILE)
    try:
        run, n_sync = read_run(out_dir, vehicle)
    except (OSError, KeyError, ValueError) as err:
        raise ConfigError(f"{out_dir}: cannot read the run: {err}") from err
    cal = Calibration(transport)
    summary = json.loads((out_dir / "summary.json").read_text(encoding="utf-8"))
    if summary.get("ended_by") != "duration":
        cal.run_ok, cal.run_note = False, f"the run ended early: {summary.get('ended_by')}"
    cal.checks = clock_checks(truth, run) + duration_checks(truth, run)
    cal.faults, cal.others = fault_checks(truth, run)
    cal.overhead = overhead(truth, run, clock_sync_samples=n_sync, wall_s=float(summary.get("wall_time_s", 0.0)))
    cal.overhead["anomalies_from_harness_delays"] = sum(1 for o in cal.others if o.cause is Cause.HARNESS)
    return cal


def calibrate(cfg: RunConfig, *, out_dir: Path, gl_backend: str, transport: Transport | None = None) -> Calibration:
    """Run ``cfg`` against the reference target and check it (see the module doc).

    Raises:
        ConfigError, TargetError: as ``hil.harness.run.driver.execute``; ConfigError as ``evaluate``.
    """
    from hil.harness.run.driver import execute, prepare_out_dir

    run_cfg = calibration_config(cfg, truth_path=(out_dir / TRUTH_FILE).resolve(), transport=transport)
    out = prepare_out_dir(out_dir)  # after the config is known good: nothing made for a bad one
    execute(run_cfg, out_dir=out, gl_backend=gl_backend, install_signal_handlers=False)
    cal = evaluate(out, transport=run_cfg.target.transport.value)
    (out / "calibration.json").write_text(json.dumps(cal.to_json(), indent=2), encoding="utf-8")
    return cal


def _fmt(v: float | None, unit: str) -> str:
    if v is None:
        return "-"
    return f"{v:+.1f} ppm" if unit == "ppm" else f"{v:.4f}" if unit == "ms" else f"{v:g} {unit}"


def render(cal: Calibration) -> str:
    """The verdict as text lines (what ``hil calibrate`` prints)."""
    lines = [f"hil calibrate: transport {cal.transport}",
             f"{'figure':<48} {'reported':>14} {'truth':>14} {'error':>11} {'bound':>11}  verdict"]
    for c in cal.checks:
        err = "-" if c.error is None else (f"{c.error * 1e3:+.1f} µs" if c.unit == "ms" else _fmt(c.error, c.unit))
        bound = "-" if c.bound is None else (f"{c.bound * 1e3:.1f} µs" if c.unit == "ms" else _fmt(c.bound, c.unit))
        lines.append(f"{c.figure:<48} {_fmt(c.reported, c.unit):>14} {_fmt(c.truth, c.unit):>14} {err:>11} "
                     f"{bound:>11}  {'ok' if c.ok else 'OUTSIDE'}" + (f"  ({c.note})" if c.note else ""))
    lines.append("injected faults (each must be flagged exactly once):")
    for f in cal.faults:
        at = "" if f.frame_id is None else f" at frame {f.frame_id}"
        lines.append(f"  {f.fault + at:<34} {', '.join(f.flagged_by) or 'not flagged':<40} "
                     f"{'ok' if f.ok else 'FAIL'}" + (f"  ({f.note})" if f.note else ""))
    lines.append(f"{'anomaly kind':<20} {'injected':>8} {'flagged there':>13} {'real elsewhere':>14} "
                 f"{'false alarms':>12}")
    for kind, row in kind_table(cal.faults, cal.others).items():
        bad = row["flagged_where_injected"] != row["injected"] or row["false_alarms"]
        lines.append(f"{kind:<20} {row['injected']:>8} {row['flagged_where_injected']:>13} "
                     f"{row['real_elsewhere']:>14} {row['false_alarms']:>12}" + ("  FAIL" if bad else ""))
    if cal.others:
        lines.append("anomalies not injected (judged against the truth):")
        lines += [f"  {o}" for o in cal.others]
    o = cal.overhead
    if o:
        def q(d: dict[str, Any]) -> str:
            return f"p50 {d['p50_ms']} ms, p99 {d['p99_ms']} ms, max {d['max_ms']} ms"
        lines.append("measuring overhead of the harness:")
        lines.append(f"  receipt lag (true send → t0'):   {q(o['receipt_lag'])}")
        lines.append(f"  true uplink (t_tx → receipt):    {q(o['true_uplink'])}")
        lines.append(f"  capture → send (t0 → t_tx):      {q(o['capture_to_send'])}")
        lines.append(f"  clock sync: {o['sync_exchanges']} exchanges ({o['sync_exchanges_per_s']}/s), "
                     f"best round trip {o['best_sync_round_trip_ms']} ms")
        n = o.get("anomalies_from_harness_delays", 0)
        if n:
            lines.append(f"  {n} anomalies above were caused by the harness's own delays (real, but not the "
                         "target's or the link's)")
    if cal.run_note:
        lines.append(cal.run_note)
    lines.append("PASS: every figure inside its bound, every fault flagged once" if cal.passed else
                 "FAIL: see the rows marked OUTSIDE / FAIL above")
    return "\n".join(lines)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("calibrate", help="check the harness's own accuracy against a reference target",
                       description="Run a reference target that injects known truth (clock offset and skew, "
                                   "inference time, spikes, a drop, a reorder, a clock step, malformed "
                                   "messages) and check every figure the harness reports against it. "
                                   "Exit 0 all inside their bounds, 1 not, 2 bad input.")
    p.add_argument("config", nargs="?", default=str(DEFAULT_CONFIG),
                   help="a config whose target is hil.targets.reference (default hil_configs/calibrate.yaml)")
    p.add_argument("--transport", choices=[Transport.LOCAL.value, Transport.ZENOH.value], default=None,
                   help="override the config's transport (zenoh: loopback, a free port)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a config field (repeatable)")
    p.add_argument("--out", type=Path, default=None, help="run folder (default runs/calibrate-<timestamp>/)")
    from hil.harness.report.ci_outputs import add_ci_args

    add_ci_args(p)


def cmd(args: argparse.Namespace) -> int:
    """Run ``hil calibrate``; returns the exit code (ConfigError propagates: exit 2)."""
    from hil.harness.report.ci_outputs import check_ci_args, write_ci_outputs
    from hil.harness.run.driver import default_out_dir
    from hil.scenarios.gl import select_backend

    check_ci_args(args)
    cfg = load_config(args.config, overrides=args.overrides)
    transport = Transport(args.transport) if args.transport else None
    out = args.out or default_out_dir(cfg)
    cal = calibrate(cfg, out_dir=out, gl_backend=select_backend(), transport=transport)
    print(render(cal))
    print(f"calibration.json: {out / 'calibration.json'}", file=sys.stderr)
    code = 0 if cal.passed else 1
    from hil.harness.check.ci_cases import of_calibrate

    write_ci_outputs(of_calibrate(cal, out=out, exit_code=code), args)
    return code

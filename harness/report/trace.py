"""``hil trace RUN [--out FILE]``: a run's timeline as a Perfetto trace
(``RUN/trace.perfetto-trace``), to open in the Perfetto UI.

What is drawn: :mod:`hil.harness.report.timeline`. How: Perfetto's own protobuf
format (``TracePacket``s of ``TrackDescriptor``s and ``TrackEvent``s), built with the
``perfetto`` package's ``StreamingTraceProtoBuilder``, one packet at a time. Each
vehicle is a process; each of its tracks a child track in :data:`timeline.TRACKS`
order. Slices on one Perfetto track must nest, so frames that overlap in a stage (a
target still busy when the next frame arrives) go to further tracks of the same name,
which the UI shows as one. Timestamps are the harness clock (``time.monotonic_ns``),
ns, on Perfetto's default trace clock.

Raises: :class:`hil.common.errors.ConfigError` (exit 2, one line) for what is not a
run folder, a recording with nothing in it, and an ``--out`` that cannot be written;
nothing is left behind then.
"""

from __future__ import annotations

import argparse
import os
from collections import defaultdict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from hil.common.errors import ConfigError
from hil.harness.record.run_folder import MCAP_NAME, read_run
from hil.harness.report.timeline import COUNTER_TRACKS, Arg, CounterPoint, Mark, Timeline, build_timeline, track_rank

TRACE_NAME = "trace.perfetto-trace"
_SEQUENCE_ID = 1  # every packet on one writer sequence
_RUN = ""         # the process of events that name no vehicle (no vehicle has an empty name)


@dataclass(frozen=True)
class TraceStats:
    """What a written trace holds: ``slices`` and ``instants`` drawn, ``tracks`` (with
    processes), ``bytes`` written."""

    slices: int
    instants: int
    tracks: int
    bytes: int


class _Tracks:
    """Track uuids: one process per vehicle (and one for run-wide events), one child
    track per (vehicle, track name, lane). Lane 0 of a name is its first track; a
    slice goes to the lowest lane free at its start."""

    def __init__(self, vehicles: list[str]) -> None:
        self.processes = {v: i + 1 for i, v in enumerate([*vehicles, _RUN])}
        self.names: dict[tuple[str, str], int] = {}
        self.lane_end: dict[tuple[str, str], list[int]] = defaultdict(list)
        self.declared: dict[int, tuple[str, str, int]] = {}

    def process_uuid(self, who: str) -> int:
        return self.processes[who] << 40

    def uuid(self, who: str, track: str, lane: int) -> int:
        key = (who, track)
        idx = self.names.setdefault(key, len([k for k in self.names if k[0] == who]) + 1)
        u = self.process_uuid(who) | (idx << 20) | lane
        self.declared.setdefault(u, (who, track, lane))
        return u

    def place(self, who: str, track: str, start: int, end: int | None) -> int:
        """The uuid of the lane ``[start, end]`` goes on (an instant: lane 0)."""
        ends = self.lane_end[(who, track)]
        if end is None:
            return self.uuid(who, track, 0)
        for lane, last in enumerate(ends):
            if last <= start:
                ends[lane] = end
                return self.uuid(who, track, lane)
        ends.append(end)
        return self.uuid(who, track, len(ends) - 1)


def _events(tl: Timeline, tracks: _Tracks) -> Iterator[tuple[int, int, str, Any]]:
    """(timestamp, order, kind, payload) of every track event, each lane's in the order
    it must be read (a slice's end before the next one's begin at the same instant)."""
    order = 0
    for m in sorted(tl.marks, key=lambda m: (m.start_ns, m.end_ns if m.end_ns is not None else m.start_ns)):
        who = _RUN if m.vehicle is None else m.vehicle
        uuid = tracks.place(who, m.track, m.start_ns, m.end_ns)
        if m.end_ns is None:
            yield m.start_ns, order, "instant", (uuid, m)
        else:
            yield m.start_ns, order, "begin", (uuid, m)
            order += 1
            yield m.end_ns, order, "end", (uuid, m)
        order += 1
    for c in tl.counters:
        yield c.t_ns, order, "counter", (tracks.uuid(c.vehicle, c.track, 0), c)
        order += 1


def _annotate(ev: Any, args: Mapping[str, Arg]) -> None:
    for k, v in args.items():
        a = ev.debug_annotations.add()
        a.name = k
        if isinstance(v, bool):
            a.bool_value = v
        elif isinstance(v, int) and -(2**63) <= v < 2**63:
            a.int_value = v
        elif isinstance(v, (int, float)):
            a.double_value = float(v)
        else:
            a.string_value = str(v)


def write_trace(tl: Timeline, out: IO[bytes]) -> TraceStats:
    """Write ``tl`` to ``out`` as a Perfetto trace. Returns what it holds."""
    from perfetto.protos.perfetto.trace.perfetto_trace_pb2 import CounterDescriptor, TrackDescriptor, TrackEvent
    from perfetto.trace_builder.proto_builder import StreamingTraceProtoBuilder

    builder = StreamingTraceProtoBuilder(out)
    tracks = _Tracks(tl.vehicles)
    events = sorted(_events(tl, tracks), key=lambda e: (e[0], e[1]))  # places every mark: tracks now known
    used = {w for w, _t, _l in tracks.declared.values()}
    for who, pid in tracks.processes.items():
        if who not in used:
            continue
        p = builder.create_packet()
        d = p.track_descriptor
        d.uuid = tracks.process_uuid(who)
        d.process.pid = pid
        d.process.process_name = who if who != _RUN else "run (events naming no vehicle)"
        d.child_ordering = TrackDescriptor.ChildTracksOrdering.EXPLICIT
        builder.write_packet(p)
    for uuid, (who, track, _lane) in sorted(tracks.declared.items()):
        p = builder.create_packet()
        d = p.track_descriptor
        d.uuid, d.parent_uuid, d.name = uuid, tracks.process_uuid(who), track
        d.sibling_order_rank = track_rank(track)
        if track in COUNTER_TRACKS:
            d.counter.unit = CounterDescriptor.Unit.UNIT_TIME_NS
        builder.write_packet(p)
    slices = instants = 0
    for ts, _order, kind, (uuid, item) in events:
        p = builder.create_packet()
        p.timestamp = ts
        p.trusted_packet_sequence_id = _SEQUENCE_ID
        ev = p.track_event
        ev.track_uuid = uuid
        if kind == "counter":
            assert isinstance(item, CounterPoint)
            ev.type = TrackEvent.Type.TYPE_COUNTER
            ev.counter_value = item.value
        elif kind == "end":
            ev.type = TrackEvent.Type.TYPE_SLICE_END
        else:
            assert isinstance(item, Mark)
            ev.type = TrackEvent.Type.TYPE_INSTANT if kind == "instant" else TrackEvent.Type.TYPE_SLICE_BEGIN
            ev.name = item.name
            _annotate(ev, item.args)
            ev.flow_ids.extend(item.flows)
            ev.terminating_flow_ids.extend(item.ends_flows)
            slices += kind == "begin"
            instants += kind == "instant"
        builder.write_packet(p)
    return TraceStats(slices, instants, len(tracks.declared) + len(used), out.tell())


def trace_run(run: str | os.PathLike[str], out: Path | None = None) -> tuple[Path, TraceStats, Timeline, Any]:
    """Read the run folder ``run`` and write its trace to ``out`` (default
    ``RUN/trace.perfetto-trace``), whole or not at all.

    Raises:
        ConfigError: not a run folder, no ``run.mcap`` or nothing in it, ``out``
            cannot be written.
    """
    data = read_run(run)
    if not data.mcap_present:
        raise ConfigError(f"{data.run_dir}: no {MCAP_NAME}: nothing to draw")
    tl = build_timeline(data)
    path = out if out is not None else data.run_dir / TRACE_NAME
    if path.is_dir():
        raise ConfigError(f"--out {path}: is a folder; name the trace file, e.g. {path / TRACE_NAME}")
    tmp = path.with_name(f".{path.name}.partial")
    try:
        with open(tmp, "wb") as f:
            stats = write_trace(tl, f)
        os.replace(tmp, path)
    except OSError as err:
        if tmp.parent.is_dir():
            tmp.unlink(missing_ok=True)
        raise ConfigError(f"cannot write trace {path}: {err.strerror or err}") from err
    return path, stats, tl, data


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``hil trace`` on the CLI's subparsers."""
    p = sub.add_parser("trace", help="write a run's frames, clock sync and events as a Perfetto trace",
                       description="Every frame of a run as slices on per-vehicle tracks (physics, render, "
                                   "capture, uplink, target queue, inference, downlink, apply), linked by flows, "
                                   "with clock-sync exchanges and events; open the file in ui.perfetto.dev "
                                   "(it runs in the browser: the trace is not uploaded).")
    p.add_argument("run", help="a run folder (or its run.mcap / summary.json)")
    p.add_argument("--out", type=Path, default=None, help=f"the trace file (default RUN/{TRACE_NAME})")


def cmd(args: argparse.Namespace) -> int:
    """``hil trace``: 0 when written; ConfigError (exit 2) for a bad input."""
    path, stats, tl, data = trace_run(Path(args.run), args.out)
    frames = sum(tl.frames.values())
    print(f"trace: {path} ({frames} frames of {len(tl.frames)} vehicle(s), {stats.slices} slices, "
          f"{stats.instants} instants, {stats.bytes / 1e3:.0f} KB)")
    print("open it at https://ui.perfetto.dev (Open trace file; the page runs in the browser, nothing is uploaded)")
    if data.truncated:
        print(f"note: {data.run_dir / MCAP_NAME} is truncated; drawn from its {data.messages} complete messages")
    if data.summary_problem:
        print(f"note: {data.summary_problem}")
    for n in tl.notes:
        print(f"note: {n}")
    return 0


__all__ = ["TRACE_NAME", "TraceStats", "add_parser", "cmd", "trace_run", "write_trace"]

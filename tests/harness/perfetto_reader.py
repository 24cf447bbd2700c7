"""A Perfetto trace read back independently of the code that wrote it: protobuf's
generic descriptor machinery (a fresh ``DescriptorPool`` and ``message_factory``) over
Perfetto's published trace schema ``protos/perfetto/trace/perfetto_trace.proto``, the
``FileDescriptorProto`` upstream compiled into the ``perfetto`` package (0.59.1). The
writer's message classes live in the default pool and are not used; every field read
must be one the schema knows (no unknown fields). Slices are rebuilt from their
begin and end events, and no two may overlap on one track.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any


@lru_cache(maxsize=1)
def _trace_class() -> Any:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from perfetto.protos.perfetto.trace import perfetto_trace_pb2 as published

    fdp = descriptor_pb2.FileDescriptorProto.FromString(published.DESCRIPTOR.serialized_pb)
    assert fdp.name == "protos/perfetto/trace/perfetto_trace.proto" and not fdp.dependency
    pool = descriptor_pool.DescriptorPool()  # not the default pool the writer's classes live in
    pool.Add(fdp)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("perfetto.protos.Trace"))


def _no_unknown_fields(msg: Any, where: str) -> None:
    from google.protobuf.unknown_fields import UnknownFieldSet

    assert len(UnknownFieldSet(msg)) == 0, f"{where}: fields the published schema does not have"
    for f, value in msg.ListFields():
        if f.message_type is None:
            continue
        for i, m in enumerate(value if f.is_repeated else [value]):
            _no_unknown_fields(m, f"{where}.{f.name}[{i}]")


@dataclass
class Slice:
    process: str
    track: str
    uuid: int
    name: str
    start: int
    end: int | None  # None: an instant
    args: dict[str, Any]
    flows: list[int]
    ends: list[int]


@dataclass
class Decoded:
    processes: dict[int, str] = field(default_factory=dict)          # uuid -> process name
    tracks: dict[int, tuple[str, str]] = field(default_factory=dict)  # uuid -> (process, track name)
    counter_tracks: set[int] = field(default_factory=set)
    marks: list[Slice] = field(default_factory=list)
    counters: list[tuple[str, str, int, int]] = field(default_factory=list)

    def of(self, process: str) -> list[Slice]:
        return [m for m in self.marks if m.process == process]


def decode(path: Path) -> Decoded:
    trace = _trace_class().FromString(path.read_bytes())
    out = Decoded()
    open_: dict[int, Slice] = {}
    last_ts = 0
    for i, p in enumerate(trace.packet):
        _no_unknown_fields(p, f"packet[{i}]")
        if p.HasField("track_descriptor"):
            d = p.track_descriptor
            if d.HasField("process"):
                out.processes[d.uuid] = d.process.process_name
            else:
                assert d.parent_uuid in out.processes, "a track before its process"
                out.tracks[d.uuid] = (out.processes[d.parent_uuid], d.name)
                if d.HasField("counter"):
                    out.counter_tracks.add(d.uuid)
            continue
        assert p.HasField("track_event") and p.trusted_packet_sequence_id == 1
        assert p.timestamp >= last_ts, "packets out of time order"
        last_ts = p.timestamp
        ev = p.track_event
        process, track = out.tracks[ev.track_uuid]
        kind = ev.Type.Name(ev.type)
        if kind == "TYPE_COUNTER":
            assert ev.track_uuid in out.counter_tracks
            out.counters.append((process, track, p.timestamp, ev.counter_value))
            continue
        if kind == "TYPE_SLICE_END":
            s = open_.pop(ev.track_uuid)
            s.end = p.timestamp
            continue
        args = {a.name: next(v for f, v in a.ListFields() if f.name != "name") for a in ev.debug_annotations}
        s = Slice(process, track, ev.track_uuid, ev.name, p.timestamp, None, args, list(ev.flow_ids),
                  list(ev.terminating_flow_ids))
        out.marks.append(s)
        if kind == "TYPE_SLICE_BEGIN":
            assert ev.track_uuid not in open_, f"slices overlap on one track: {track} of {process}"
            open_[ev.track_uuid] = s
        else:
            assert kind == "TYPE_INSTANT", kind
    assert not open_, "a slice never ended"
    return out

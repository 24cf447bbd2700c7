"""Everything a run says happened: one typed event model, and the one bus it travels on.

An :class:`Event` carries the fields DESIGN.md promises every event has: ``kind``,
``vehicle``, ``frame_ids``, ``sim_time_ns`` and ``harness_time_ns``, ``measured``
against ``threshold`` (in ``unit``), ``severity``, ``cause`` and ``links`` (the
``kind@frame`` of related events: a mismatch's timing anomalies). ``detail`` is one
sentence for a person; what only one kind has (a protocol error's byte offset, a
mismatch's evidence, a command's text) goes in ``extra``. Timing anomalies
(:class:`hil.timing.anomaly.Anomaly`) and corner-case mismatches
(:class:`hil.harness.cases.detector.Mismatch`) map into it; collisions, commands,
protocol errors, late or unknown estimates and lockstep replay outcomes are built as
events where they happen.

:class:`EventBus` is the one in-process path from those who find events to those who
keep them: the recorder (``/events``, schema :data:`EVENT_SCHEMA`; the live view and
Foxglove's ``/log`` are fed from that channel) and the corner-case recorder subscribe.
Publish from the analysis thread only: subscribers run there, in the order they
subscribed, so the recording and the cases see events in one order.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Any, Protocol

from hil.timing.anomaly import Anomaly, Severity

if TYPE_CHECKING:
    from hil.harness.cases.detector import Mismatch

MISMATCH_PREFIX = "mismatch."


class EventKind(str, Enum):
    """Every kind of event, by family. The values are what ``/events`` carries."""

    # timing anomalies (hil.timing.anomaly.AnomalyKind, same values)
    DEADLINE_MISS = "deadline_miss"
    JITTER = "jitter"
    DROPPED_FRAME = "dropped_frame"
    STALE_ESTIMATE = "stale_estimate"
    OUT_OF_ORDER = "out_of_order"
    FRAME_RATE_FLOOR = "frame_rate_floor"
    LATENCY_SPIKE = "latency_spike"
    CLOCK_STEP = "clock_step"
    SKEW_LIMIT = "skew_limit"
    SYNC_LOST = "sync_lost"
    CAUSALITY = "causality"
    # a vehicle's camera rig (hil.timing.rig.RigTracker), each flagged once at the
    # frame set where it begins
    RIG_DESYNC = "rig_desync"          # capture skew or arrival spread of a set over its threshold
    CAMERA_MISSING = "camera_missing"  # a set settled without one of its cameras
    CAMERA_LATE = "camera_late"        # one camera's end-to-end persistently above the rest of the rig's
    # state mismatches against ground truth (hil.harness.cases.detector.MismatchKind)
    POSITION_ERROR = "mismatch.position_error"
    MISSED_OBJECT = "mismatch.missed_object"
    GHOST_OBJECT = "mismatch.ghost_object"
    STATE_MISMATCH = "mismatch.state_mismatch"
    COLLISION_WHILE_SAFE = "mismatch.collision_while_safe"
    LATE_REACTION = "mismatch.late_reaction"
    # estimates that matched no frame in flight (after its drop, or never sent)
    LATE_ESTIMATE = "late_estimate"
    UNKNOWN_ESTIMATE = "unknown_estimate"
    # the world
    COLLISION = "collision"
    # commands to the target and its replies
    TARGET_COMMAND = "target_command"
    TARGET_COMMAND_REPLY = "target_command_reply"
    TARGET_COMMAND_FAILED = "target_command_failed"
    # the wire and the target's own errors
    PROTOCOL_ERROR = "protocol_error"
    TARGET_ERROR = "target_error"
    # lockstep replay with a recorded latency profile: what became of each frame
    REPLAYED_OK = "replayed_ok"
    REPLAYED_DROPPED = "replayed_dropped"
    REPLAYED_STALE = "replayed_stale"
    REPLAYED_PENDING = "replayed_pending"
    # the harness itself: a process that could not keep up with the physics's rings
    CONSUMER_BEHIND = "consumer_behind"
    # a rig of several cameras whose target did not announce CAP_CAMERAS: camera 0 only
    RIG_CAMERA_ZERO_ONLY = "rig_camera_zero_only"

    @property
    def is_mismatch(self) -> bool:
        return self.value.startswith(MISMATCH_PREFIX)

    @property
    def family(self) -> str:
        """What the kind belongs to (README "What a run writes"): ``anomaly`` (timing,
        counted in ``vehicles.<name>.anomalies``), ``mismatch``, ``estimate``,
        ``world``, ``command``, ``protocol``, ``target``, ``replay`` or ``harness``."""
        return _FAMILY.get(self, "anomaly")


_FAMILY: Mapping[EventKind, str] = {
    **{k: "mismatch" for k in EventKind if k.value.startswith(MISMATCH_PREFIX)},
    EventKind.LATE_ESTIMATE: "estimate", EventKind.UNKNOWN_ESTIMATE: "estimate",
    EventKind.COLLISION: "world",
    EventKind.TARGET_COMMAND: "command", EventKind.TARGET_COMMAND_REPLY: "command",
    EventKind.TARGET_COMMAND_FAILED: "command",
    EventKind.PROTOCOL_ERROR: "protocol", EventKind.TARGET_ERROR: "target",
    **{k: "replay" for k in EventKind if k.value.startswith("replayed_")},
    EventKind.CONSUMER_BEHIND: "harness", EventKind.RIG_CAMERA_ZERO_ONLY: "target",
}

# Severity of the kinds that do not carry their own (anomalies and mismatches do).
DEFAULT_SEVERITY: Mapping[EventKind, Severity] = {
    EventKind.COLLISION: Severity.CRITICAL,
    EventKind.PROTOCOL_ERROR: Severity.WARNING,
    EventKind.TARGET_ERROR: Severity.WARNING,
    EventKind.LATE_ESTIMATE: Severity.WARNING,
    EventKind.UNKNOWN_ESTIMATE: Severity.WARNING,
    EventKind.TARGET_COMMAND_FAILED: Severity.WARNING,
    EventKind.REPLAYED_DROPPED: Severity.WARNING,
    EventKind.REPLAYED_STALE: Severity.WARNING,
    EventKind.REPLAYED_PENDING: Severity.WARNING,
    EventKind.CONSUMER_BEHIND: Severity.WARNING,
    EventKind.RIG_CAMERA_ZERO_ONLY: Severity.WARNING,
    EventKind.RIG_DESYNC: Severity.WARNING,
    EventKind.CAMERA_MISSING: Severity.WARNING,
    EventKind.CAMERA_LATE: Severity.WARNING,
}


@dataclass(frozen=True)
class Event:
    """One event. Times are harness-clock (``harness_time_ns``) and simulation
    (``sim_time_ns``, ``None`` where nothing in the simulation is involved)
    nanoseconds; ``vehicle`` is ``None`` for the whole run (a collision between two
    actors names no single vehicle)."""

    kind: EventKind
    harness_time_ns: int
    vehicle: str | None = None
    frame_ids: tuple[int, ...] = ()
    sim_time_ns: int | None = None
    measured: float | None = None
    threshold: float | None = None
    unit: str | None = None
    severity: Severity = Severity.INFO
    cause: str | None = None
    links: tuple[str, ...] = ()
    detail: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def of(cls, kind: EventKind, harness_time_ns: int, **fields: Any) -> Event:
        """An event with its kind's default severity unless ``severity`` is given."""
        fields.setdefault("severity", DEFAULT_SEVERITY.get(kind, Severity.INFO))
        return cls(kind, harness_time_ns, **fields)

    @classmethod
    def from_anomaly(cls, a: Anomaly, vehicle: str) -> Event:
        return cls(EventKind(a.kind.value), a.harness_time_ns, vehicle, tuple(a.frame_ids), a.sim_time_ns,
                   a.measured, a.threshold, a.unit, a.severity, a.cause, (), a.detail,
                   {"stage": a.stage} if a.stage is not None else {})

    @classmethod
    def from_mismatch(cls, m: Mismatch) -> Event:
        return cls(EventKind(MISMATCH_PREFIX + m.kind.value), m.harness_time_ns, m.vehicle, tuple(m.frame_ids),
                   m.sim_time_ns, m.measured, m.threshold, m.unit, m.severity, m.cause.value,
                   tuple(m.linked_anomalies), m.detail, {"entity": m.entity, "evidence": dict(m.evidence)})

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Event:
        """An ``/events`` message back as an Event (what is not a field goes to ``extra``).

        Raises:
            ValueError: ``kind`` or ``severity`` is not one of ours.
        """
        kind = EventKind(d["kind"])
        sev = d.get("severity")
        return cls(kind, int(d.get("harness_time_ns") or 0), d.get("vehicle"), tuple(d.get("frame_ids") or ()),
                   d.get("sim_time_ns"), d.get("measured"), d.get("threshold"), d.get("unit"),
                   Severity(sev) if sev is not None else DEFAULT_SEVERITY.get(kind, Severity.INFO), d.get("cause"),
                   tuple(d.get("links") or ()), str(d.get("detail") or ""),
                   {k: v for k, v in d.items() if k not in _FIELDS})

    def to_json(self) -> dict[str, Any]:
        """The ``/events`` message: the promised fields, then ``extra`` (which never
        overrides them)."""
        out: dict[str, Any] = {k: v for k, v in self.extra.items() if k not in _FIELDS}
        out.update(kind=self.kind.value, vehicle=self.vehicle, frame_ids=list(self.frame_ids),
                   sim_time_ns=self.sim_time_ns, harness_time_ns=self.harness_time_ns, measured=self.measured,
                   threshold=self.threshold, unit=self.unit, severity=self.severity.value, cause=self.cause,
                   links=list(self.links), detail=self.detail)
        return out


_FIELDS = frozenset(f for f in Event.__dataclass_fields__ if f != "extra")

# The JSON schema of /events: the promised fields are always there; extras may follow.
_NUM = {"type": ["number", "null"]}
EVENT_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "kind": {"type": "string", "enum": [k.value for k in EventKind]},
        "vehicle": {"type": ["string", "null"]},
        "frame_ids": {"type": "array", "items": {"type": "integer"}},
        "sim_time_ns": {"type": ["integer", "null"]},
        "harness_time_ns": {"type": "integer"},
        "measured": _NUM,
        "threshold": _NUM,
        "unit": {"type": ["string", "null"]},
        "severity": {"type": "string", "enum": [s.value for s in Severity]},
        "cause": {"type": ["string", "null"]},
        "links": {"type": "array", "items": {"type": "string"}},
        "detail": {"type": "string"},
    },
    "required": sorted(_FIELDS),
}

# A subscriber gets the event and its log time: when it was known (harness ns), which
# is its harness_time_ns unless it was found later (a replayed frame's fate).
Subscriber = Callable[[Event, int], None]


class JsonSink(Protocol):
    """Where JSON messages are written (the run's Recorder, a corner-case recorder in
    front of it, or a shard's encoding recorder): write-only."""

    def write_json(self, topic: str, obj: Mapping[str, Any], *, log_time_ns: int, publish_time_ns: int) -> bool: ...


class EventBus:
    """Publishers hand events to every subscriber, in subscription order. Not
    thread-safe by design: one thread (the analysis thread) publishes."""

    def __init__(self) -> None:
        self._subscribers: list[Subscriber] = []
        self.published = 0
        self.unrecorded = 0  # events the recording subscriber could not write (queue full)
        self._counts: dict[tuple[str | None, str], int] = {}

    def subscribe(self, fn: Subscriber) -> None:
        self._subscribers.append(fn)

    def counts(self, vehicle: str | None) -> dict[str, int]:
        """Events published for ``vehicle`` (``None``: the whole run's), by kind."""
        return dict(sorted((k, n) for (v, k), n in self._counts.items() if v == vehicle))

    def publish(self, ev: Event, log_time_ns: int | None = None) -> None:
        self.published += 1
        key = (ev.vehicle, ev.kind.value)
        self._counts[key] = self._counts.get(key, 0) + 1
        t = ev.harness_time_ns if log_time_ns is None else log_time_ns
        for fn in self._subscribers:
            fn(ev, t)

    @classmethod
    def recording_to(cls, rec: JsonSink) -> EventBus:
        """A bus whose first subscriber writes every event on ``/events`` of ``rec``
        (publish time: when it happened; log time: when it was known)."""
        bus = cls()

        def write(ev: Event, log_time_ns: int) -> None:
            if not rec.write_json("/events", ev.to_json(), log_time_ns=log_time_ns,
                                  publish_time_ns=ev.harness_time_ns):
                bus.unrecorded += 1

        bus.subscribe(write)
        return bus


__all__ = ["DEFAULT_SEVERITY", "EVENT_SCHEMA", "Event", "EventBus", "EventKind", "JsonSink", "MISMATCH_PREFIX",
           "Subscriber"]

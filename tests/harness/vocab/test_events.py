"""One event model (issue 13 item 2): every anomaly and mismatch kind has an event
kind, every event carries the promised fields and validates against the one
``/events`` schema, the bus hands events to its subscribers in order, and a real run
with injected faults writes only such events."""

from __future__ import annotations

import sys

import jsonschema
import pytest

from hil.harness.cases.detector import Cause, Mismatch, MismatchKind
from hil.harness.vocab.events import EVENT_SCHEMA, Event, EventBus, EventKind
from hil.harness.config.loading import load_config
from hil.harness.run.driver import execute, prepare_out_dir
from hil.timing.anomaly import Anomaly, AnomalyKind, Severity
from tests.conftest import GL_BACKEND, read_mcap

PROMISED = {"kind", "vehicle", "frame_ids", "sim_time_ns", "harness_time_ns", "measured", "threshold", "unit",
            "severity", "cause", "links", "detail"}


def anomaly(kind: AnomalyKind) -> Anomaly:
    return Anomaly(kind, "ego0", (7, 8), 400_000_000, 1_234_000_000, 31.5, 25.0, "ms", Severity.CRITICAL,
                   stage="end_to_end", detail="late")


def mismatch(kind: MismatchKind) -> Mismatch:
    return Mismatch(kind, Cause.LATENCY, "ego0", (9,), 450_000_000, 1_300_000_000, 2.5, 1.0, "m",
                    Severity.WARNING, entity="car1", detail="off", linked_anomalies=("deadline_miss@8",),
                    evidence={"gap_m": 4.0})


def test_the_schema_promises_the_fields_design_md_names():
    assert set(EVENT_SCHEMA["required"]) == PROMISED


@pytest.mark.parametrize("kind", list(AnomalyKind))
def test_every_anomaly_is_an_event(kind: AnomalyKind):
    ev = Event.from_anomaly(anomaly(kind), "ego0")
    d = ev.to_json()
    jsonschema.validate(d, EVENT_SCHEMA)
    assert d["kind"] == kind.value and ev.kind.value == kind.value and not ev.kind.is_mismatch
    assert (d["frame_ids"], d["measured"], d["threshold"], d["unit"], d["severity"], d["stage"]) == \
        ([7, 8], 31.5, 25.0, "ms", "critical", "end_to_end")
    assert Event.from_json(d) == ev


@pytest.mark.parametrize("kind", list(MismatchKind))
def test_every_mismatch_is_an_event(kind: MismatchKind):
    ev = Event.from_mismatch(mismatch(kind))
    d = ev.to_json()
    jsonschema.validate(d, EVENT_SCHEMA)
    assert d["kind"] == f"mismatch.{kind.value}" and ev.kind.is_mismatch
    assert (d["cause"], d["links"], d["evidence"], d["entity"]) == ("latency", ["deadline_miss@8"], {"gap_m": 4.0},
                                                                     "car1")
    assert Event.from_json(d) == ev


def test_extras_never_override_the_promised_fields():
    ev = Event.of(EventKind.PROTOCOL_ERROR, 5, vehicle="ego0", extra={"kind": "forged", "severity": "info",
                                                                      "offset": 12})
    d = ev.to_json()
    assert (d["kind"], d["severity"], d["offset"]) == ("protocol_error", "warning", 12)


def test_a_kind_that_is_not_ours_is_refused():
    with pytest.raises(ValueError):
        Event.from_json({"kind": "note", "harness_time_ns": 1})
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**Event.of(EventKind.COLLISION, 1).to_json(), "kind": "note"}, EVENT_SCHEMA)


def test_the_bus_serves_subscribers_in_order_with_the_log_time():
    bus, seen = EventBus(), []
    bus.subscribe(lambda ev, t: seen.append(("first", ev.kind.value, t)))
    bus.subscribe(lambda ev, t: seen.append(("second", ev.kind.value, t)))
    bus.publish(Event.of(EventKind.TARGET_COMMAND, 10))
    bus.publish(Event.of(EventKind.REPLAYED_DROPPED, 20), log_time_ns=25)
    assert seen == [("first", "target_command", 10), ("second", "target_command", 10),
                    ("first", "replayed_dropped", 25), ("second", "replayed_dropped", 25)]
    assert bus.published == 2


@pytest.mark.slow
def test_a_run_with_faults_writes_only_schema_events(tmp_path):
    # The reference target injects a drop, a reordered pair, a bad CRC and a bad
    # length field: timing anomalies and protocol errors from one run.
    cfg = load_config("hil_configs/calibrate.yaml", overrides=[
        "duration_s=4", "progress=false",
        f'target.command=["{sys.executable}", "-m", "hil.targets.reference"]',
        'target.args=["--drop-frames", "10", "--reorder-frames", "20", '
        '"--bad-crc-frames", "30", "--bad-length-frames", "40"]'])  # 4 s at 12.5 fps: frames 0-49
    out = prepare_out_dir(tmp_path / "r")
    execute(cfg, out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    events = [d for _, d in read_mcap(out / "run.mcap")["/events"]]  # read_mcap validates each one
    kinds = {d["kind"] for d in events}
    assert {"dropped_frame", "stale_estimate", "protocol_error"} <= kinds, kinds
    for d in events:
        assert PROMISED <= d.keys()
        assert Event.from_json(d).to_json() == d


def test_the_bus_counts_events_of_vehicles_and_of_the_run_apart() -> None:
    # A collision names no vehicle: counting it beside vehicle names must not compare None with a name.
    from hil.harness.vocab.events import Event, EventBus, EventKind

    bus = EventBus()
    bus.publish(Event.of(EventKind.COLLISION, 1))
    bus.publish(Event.of(EventKind.LATENCY_SPIKE, 2, vehicle="ego1"))
    bus.publish(Event.of(EventKind.DROPPED_FRAME, 3, vehicle="ego0"))
    bus.publish(Event.of(EventKind.DEADLINE_MISS, 4, vehicle="ego0"))
    assert bus.counts(None) == {"collision": 1}
    assert bus.counts("ego0") == {"deadline_miss": 1, "dropped_frame": 1}
    assert bus.counts("ego1") == {"latency_spike": 1} and bus.published == 4

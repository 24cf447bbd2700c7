"""Corner-case windows cut out of a finished run: ``corner_cases/case-NNNN.mcap``.

A case row (``hil.harness.cases.casebook``) refers to ``run.mcap`` and a window in sim
time, ``[window_start_ns, window_end_ns]``. :func:`write_case_windows` reads
``run.mcap`` once, in file order (a crashed run's file too, up to its last complete
chunk), and copies into each case's file the messages recorded while the simulation
was inside its window: the shared topics (``/ground_truth``, ``/events``, ``/scene``,
``/tf``, ``/log``, any other that is not a vehicle's) and the case vehicle's own
(``/<vehicle>/...``), never the other vehicles'.

A message's sim time is that of the latest ``/ground_truth`` before it in the file;
an event's is its own ``sim_time_ns`` where it has one (events are written late, once
the timing analysis of their frames is done). Messages are copied as recorded (no
re-encoding), except the window's first ``/ground_truth``, written with every
entity's state (``initial: true``) so the window stands alone (the run records only
what changed); the run's metadata records (run, config, time anchor) are copied and
a ``case`` record added (id, vehicle, window). The row's ``mcap_path`` and
``messages`` then name the window file. At most ``limit`` windows per call: disk
stays bounded whatever the number of cases; the rest keep referring to ``run.mcap``.
"""

from __future__ import annotations

import json
import sqlite3
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from hil.common.errors import ConfigError
from hil.harness.cases.casebook import DB_NAME, FOLDER, RUN_MCAP
from hil.harness.record.recorder import iter_salvaged_messages

MAX_WINDOWS = 16  # window files written by one call (bounded disk)
_PER_VEHICLE = ("pipeline", "estimate", "camera")  # "/<vehicle>/<these>" name a vehicle


@dataclass
class _Window:
    id: int
    vehicle: str
    start_ns: int
    end_ns: int
    rel: str
    writer: Writer
    file: Any
    schemas: dict[int, int] = field(default_factory=dict)
    channels: dict[int, int] = field(default_factory=dict)
    messages: int = 0
    started: bool = False


def write_case_windows(run_dir: Path, *, case_ids: list[int] | None = None, limit: int = MAX_WINDOWS) -> list[str]:
    """Write the windows of ``case_ids`` (default: the first ``limit`` cases that
    have none yet); returns one line per window that could not be written.

    Raises:
        ConfigError: no corner-case database or run.mcap, an unknown case id, a
            case asked for whose row has no window (NULL or not integers), or more
            than ``limit`` cases asked for.
    """
    db = run_dir / DB_NAME
    mcap = run_dir / RUN_MCAP
    if not db.is_file() or not mcap.is_file():
        raise ConfigError(f"{run_dir}: no {DB_NAME} or no {RUN_MCAP}: not a run folder with corner cases")
    con = sqlite3.connect(db)
    try:
        cols = {r[1] for r in con.execute("PRAGMA table_info(cases)")}
        if "window_start_ns" not in cols:
            raise ConfigError(f"{db}: cases recorded with their windows already (an older run); nothing to cut")
        rows = con.execute("SELECT id, vehicle, window_start_ns, window_end_ns, mcap_path FROM cases "
                           "ORDER BY id").fetchall()
        if case_ids is not None:
            known = {r[0] for r in rows}
            missing = [i for i in case_ids if i not in known]
            if missing:
                raise ConfigError(f"{run_dir}: no corner case {missing[0]} (cases: "
                                  f"{', '.join(str(i) for i in sorted(known)) or 'none'})")
            if len(case_ids) > limit:
                raise ConfigError(f"{len(case_ids)} windows asked for; at most {limit} at a time")
            todo = [r for r in rows if r[0] in set(case_ids)]
        else:
            todo = [r for r in rows if r[4] == RUN_MCAP][:limit]
        errors: list[str] = []
        usable = []
        for row in todo:  # a damaged (or tampered) row: one line, not a TypeError
            cid, start, end = row[0], row[2], row[3]
            if isinstance(start, int) and isinstance(end, int) and start <= end:
                usable.append(row)
                continue
            line = (f"{db}: case {cid} has no window in {RUN_MCAP} (window_start_ns {start!r}, window_end_ns "
                    f"{end!r}): the row is damaged; nothing to cut")
            if case_ids is not None:
                raise ConfigError(line)
            errors.append(line)
        todo = usable
        if not todo:
            return errors
        (run_dir / FOLDER).mkdir(exist_ok=True)
        windows: list[_Window] = []
        try:
            for cid, vehicle, start, end, _ in todo:
                rel = f"{FOLDER}/case-{cid:04d}.mcap"
                f = open(run_dir / rel, "wb")
                writer = Writer(f, compression=CompressionType.ZSTD)
                writer.start(profile="", library="hil-harness case window")
                windows.append(_Window(cid, vehicle, int(start), int(end), rel, writer, f))
            _copy(mcap, windows)
        finally:
            for w in windows:
                try:
                    w.writer.finish()
                    w.file.close()
                except (OSError, ValueError) as err:
                    errors.append(f"case {w.id}: {err}")
        for w in windows:
            con.execute("UPDATE cases SET mcap_path = ?, messages = ? WHERE id = ?", (w.rel, w.messages, w.id))
        con.commit()
        return errors
    except sqlite3.Error as err:
        raise ConfigError(f"{db}: not a corner-case database ({err})") from err
    finally:
        con.close()


def _summary(mcap: Path) -> tuple[set[str], list[tuple[str, dict[str, str]]]]:
    """The run's vehicles (from the channels in the file's summary) and its metadata
    records; both empty for a crashed run's file (vehicles are learnt while reading)."""
    try:
        with open(mcap, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            meta = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
    except (OSError, McapError, ValueError, struct.error):
        return set(), []
    vehicles = {c.topic.split("/")[1] for c in (summary.channels.values() if summary else ())
                if c.topic.count("/") == 2 and c.topic.rsplit("/", 1)[1] in _PER_VEHICLE}
    return vehicles, meta


def _copy(mcap: Path, windows: list[_Window]) -> None:
    vehicles, meta = _summary(mcap)
    for w in windows:
        for name, record in meta:
            w.writer.add_metadata(name, record)
        w.writer.add_metadata("case", {"id": str(w.id), "vehicle": w.vehicle, "window_start_ns": str(w.start_ns),
                                       "window_end_ns": str(w.end_ns)})
    sim_ns = 0
    entities: dict[Any, dict[str, Any]] = {}  # every entity's latest state (the run records changes)
    for schema, channel, msg in iter_salvaged_messages(mcap):
        gt = None
        if channel.topic == "/ground_truth":
            try:
                gt = json.loads(msg.data)
                sim_ns = int(gt["sim_time_ns"])
                for e in gt.get("entities", ()):
                    entities[e.get("id", e.get("name"))] = e
            except (ValueError, KeyError, TypeError):
                gt = None
        at_ns = sim_ns
        if channel.topic == "/events":  # written late (after the timing analysis): its own sim time
            try:
                own = json.loads(msg.data).get("sim_time_ns")
            except (ValueError, AttributeError):
                own = None
            if isinstance(own, int):
                at_ns = own
        parts = channel.topic.split("/")
        if len(parts) == 3 and parts[2] in _PER_VEHICLE:
            vehicles.add(parts[1])
        for w in windows:
            if not (w.start_ns <= at_ns <= w.end_ns):
                continue
            if len(parts) > 2 and parts[1] in vehicles and parts[1] != w.vehicle:
                continue  # another vehicle's channel
            data = msg.data
            if gt is not None and not w.started:
                data = json.dumps({**gt, "initial": True, "entities": list(entities.values())},
                                  separators=(",", ":")).encode()
            if gt is not None:
                w.started = True
            w.writer.add_message(_channel(w, schema, channel), log_time=msg.log_time, data=data,
                                 publish_time=msg.publish_time, sequence=msg.sequence)
            w.messages += 1


def _channel(w: _Window, schema: Any, channel: Any) -> int:
    cid = w.channels.get(channel.id)
    if cid is None:
        sid = 0
        if schema is not None:
            sid = w.schemas.get(schema.id, 0)
            if not sid:
                sid = w.schemas[schema.id] = w.writer.register_schema(schema.name, schema.encoding, schema.data)
        cid = w.channels[channel.id] = w.writer.register_channel(channel.topic, channel.message_encoding, sid,
                                                                 dict(channel.metadata))
    return cid

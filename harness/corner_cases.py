"""Corner cases: the history that led to each one, kept and indexed.

``CaseRecorder`` stands in front of the run's ``Recorder`` (same methods): every
message goes to ``run.mcap`` and into a time-bounded history (the last
``history_s`` of harness time, all vehicles). A message on ``/events`` whose kind
is a trigger (every ``mismatch.*``, plus the timing-anomaly kinds named in config)
opens a case: once ``after_s`` more has been recorded (or the run ends), the window
``[trigger − history_s, trigger + after_s]`` is cut from the history and, after the
run (or once ``MAX_WAITING_WINDOWS`` wait), written to ``corner_cases/case-NNNN.mcap``
by a background thread, and a row goes to
``corner_cases.sqlite`` (table ``cases``: run, scenario, seed, params, config hash,
vehicle, sim time, kind, cause, severity, summary, window file), enough for
``hil replay`` to re-run it. Triggers within ``after_s`` of an open case of the
same vehicle and kind join it instead of opening another.
"""

from __future__ import annotations

import json
import queue
import sqlite3
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness.recorder import Recorder, RecorderStats
from timing.errors import ConfigError

DB_NAME = "corner_cases.sqlite"
MAX_WAITING_WINDOWS = 32
FOLDER = "corner_cases"

SCHEMA = """
CREATE TABLE IF NOT EXISTS cases (
    id INTEGER PRIMARY KEY,
    run TEXT NOT NULL, scenario TEXT NOT NULL, seed INTEGER NOT NULL, params TEXT NOT NULL,
    config_hash TEXT NOT NULL, vehicle TEXT NOT NULL, sim_time_ns INTEGER NOT NULL,
    harness_time_ns INTEGER NOT NULL, kind TEXT NOT NULL, cause TEXT, severity TEXT,
    summary TEXT NOT NULL, event TEXT NOT NULL, mcap_path TEXT NOT NULL, messages INTEGER NOT NULL
)
"""


@dataclass
class _Case:
    id: int
    vehicle: str
    kind: str
    event: dict[str, Any]
    t_ns: int
    due_ns: int
    joined: int = 0


@dataclass
class _Msg:
    op: str  # "json" | "image" | "raw"
    topic: str
    log_ns: int
    pub_ns: int
    args: tuple[Any, ...]
    kwargs: dict[str, Any] = field(default_factory=dict)


class CaseRecorder:
    """A ``Recorder`` stand-in that also keeps corner cases (see module docstring)."""

    def __init__(self, rec: Recorder, run_dir: Path, *, run_meta: Mapping[str, Any], history_s: float,
                 after_s: float, trigger_kinds: set[str]) -> None:
        self.rec = rec
        self.run_dir = run_dir
        self.meta = dict(run_meta)
        self.history_ns = int(history_s * 1e9)
        self.after_ns = int(after_s * 1e9)
        self.triggers = set(trigger_kinds)
        self._history: deque[_Msg] = deque()
        self._schemas: dict[str, tuple[str, Mapping[str, Any]]] = {}
        self._open: list[_Case] = []
        self._next_id = 1
        self._jobs: queue.Queue[tuple[_Case, list[_Msg]] | None] = queue.Queue()
        self._ready: list[tuple[_Case, list[_Msg]]] = []
        self._writer: threading.Thread | None = None
        self.cases_written = 0
        self.errors: list[str] = []
        self._last_ns = 0

    # -- Recorder interface ------------------------------------------------------

    def register_json_channel(self, topic: str, schema_name: str, schema: Mapping[str, Any]) -> None:
        self.rec.register_json_channel(topic, schema_name, schema)
        self._schemas[topic] = (schema_name, schema)

    def write_json(self, topic: str, obj: Mapping[str, Any], *, log_time_ns: int, publish_time_ns: int) -> bool:
        ok = self.rec.write_json(topic, obj, log_time_ns=log_time_ns, publish_time_ns=publish_time_ns)
        self._keep(_Msg("json", topic, log_time_ns, publish_time_ns, (obj,)))
        if topic == "/events":
            self._maybe_trigger(obj, log_time_ns)
        return ok

    def write_image(self, topic: str, data: bytes, *, fmt: str, frame_id: str, log_time_ns: int,
                    publish_time_ns: int) -> bool:
        ok = self.rec.write_image(topic, data, fmt=fmt, frame_id=frame_id, log_time_ns=log_time_ns,
                                  publish_time_ns=publish_time_ns)
        self._keep(_Msg("image", topic, log_time_ns, publish_time_ns, (data,), {"fmt": fmt, "frame_id": frame_id}))
        return ok

    def write_raw_image(self, topic: str, pixels: np.ndarray, *, encoding: str, frame_id: str, log_time_ns: int,
                        publish_time_ns: int) -> bool:
        ok = self.rec.write_raw_image(topic, pixels, encoding=encoding, frame_id=frame_id,
                                      log_time_ns=log_time_ns, publish_time_ns=publish_time_ns)
        self._keep(_Msg("raw", topic, log_time_ns, publish_time_ns, (pixels.copy(),),
                        {"encoding": encoding, "frame_id": frame_id}))
        return ok

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        self.rec.add_metadata(name, data)

    def flush(self, **kw: Any) -> bool:
        return self.rec.flush(**kw)

    @property
    def stats(self) -> RecorderStats:
        return self.rec.stats

    # -- cases -------------------------------------------------------------------

    def _keep(self, m: _Msg) -> None:
        self._history.append(m)
        self._last_ns = max(self._last_ns, m.log_ns)
        horizon = self._last_ns - self.history_ns - self.after_ns
        while self._history and self._history[0].log_ns < horizon:
            self._history.popleft()
        while self._open and self._open[0].due_ns <= self._last_ns:
            self._dispatch(self._open.pop(0))

    def _maybe_trigger(self, ev: Mapping[str, Any], t_ns: int) -> None:
        kind = str(ev.get("kind", ""))
        if not (kind.startswith("mismatch.") or kind in self.triggers):
            return
        vehicle = str(ev.get("vehicle", ""))
        for c in self._open:
            if c.vehicle == vehicle and c.kind == kind:
                c.joined += 1
                return
        self._open.append(_Case(self._next_id, vehicle, kind, dict(ev), t_ns, t_ns + self.after_ns))
        self._next_id += 1

    def _dispatch(self, case: _Case) -> None:
        lo, hi = case.t_ns - self.history_ns, case.t_ns + self.after_ns
        self._ready.append((case, [m for m in self._history if lo <= m.log_ns <= hi]))
        # Writing a window (JSON, base64, zstd) in a thread competes with the sim loop
        # for the GIL (a 66 ms stall measured), so windows wait for the end of the run,
        # unless so many wait that memory matters.
        if len(self._ready) >= MAX_WAITING_WINDOWS:
            self._start_writing()

    def _start_writing(self) -> None:
        if self._writer is None:
            (self.run_dir / FOLDER).mkdir(exist_ok=True)
            self._writer = threading.Thread(target=self._write_loop, name="corner-cases", daemon=True)
            self._writer.start()
        for job in self._ready:
            self._jobs.put(job)
        self._ready.clear()

    def _write_loop(self) -> None:
        con = sqlite3.connect(self.run_dir / DB_NAME)
        try:
            con.execute(SCHEMA)
            while (job := self._jobs.get()) is not None:
                case, window = job
                try:
                    self._write_case(con, case, window)
                    self.cases_written += 1
                except Exception as err:  # noqa: BLE001 - any failure must reach the summary, not end the thread
                    self.errors.append(f"case {case.id}: {type(err).__name__}: {err}")
        finally:
            con.close()

    def _write_case(self, con: sqlite3.Connection, case: _Case, window: list[_Msg]) -> None:
        rel = f"{FOLDER}/case-{case.id:04d}.mcap"
        ev = case.event
        summary = str(ev.get("detail") or ev.get("kind"))
        if case.joined:
            summary += f" (+{case.joined} more within {self.after_ns / 1e9:g} s)"
        with Recorder(self.run_dir / rel, queue_size=len(window) + 16, compression="zstd", metadata={
            "case": {"id": str(case.id), "kind": case.kind, "vehicle": case.vehicle, "event": json.dumps(ev)},
            "run": {k: v if isinstance(v, str) else json.dumps(v) for k, v in self.meta.items()},
        }) as out:
            for topic, (name, schema) in self._schemas.items():
                out.register_json_channel(topic, name, schema)
            for m in window:
                kw = dict(m.kwargs, log_time_ns=m.log_ns, publish_time_ns=m.pub_ns)
                if m.op == "json":
                    out.write_json(m.topic, *m.args, **kw)
                elif m.op == "image":
                    out.write_image(m.topic, *m.args, **kw)
                else:
                    out.write_raw_image(m.topic, *m.args, **kw)
        sim_ns = ev.get("sim_time_ns")
        con.execute(
            "INSERT INTO cases (id, run, scenario, seed, params, config_hash, vehicle, sim_time_ns, harness_time_ns,"
            " kind, cause, severity, summary, event, mcap_path, messages) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
            (case.id, str(self.meta.get("name")), str(self.meta.get("scenario")), int(self.meta.get("seed", 0)),
             json.dumps(self.meta.get("scenario_params", {}), sort_keys=True), str(self.meta.get("config_hash")),
             case.vehicle, int(sim_ns) if isinstance(sim_ns, int) else -1, case.t_ns, case.kind,
             ev.get("cause"), ev.get("severity"), summary, json.dumps(ev, default=str), rel, len(window)))
        con.commit()

    def close(self) -> None:
        """Write every open case with what was recorded, then finish the index."""
        for c in self._open:
            self._dispatch(c)
        self._open.clear()
        if self._ready:
            self._start_writing()
        if self._writer is not None:
            self._jobs.put(None)
            self._writer.join()
            self._writer = None


def query_cases(db: Path) -> list[dict[str, Any]]:
    """Every row of table ``cases`` as it is stored, by sim time then id (read-only).

    Raises:
        sqlite3.Error: not a database, or no table ``cases``.
    """
    con = sqlite3.connect(f"{db.resolve().as_uri()}?mode=ro", uri=True)
    try:
        con.row_factory = sqlite3.Row
        return [dict(r) for r in con.execute("SELECT * FROM cases ORDER BY sim_time_ns, id")]
    finally:
        con.close()


def read_cases(run_dir: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """The cases of a run, and one warning line per row that could not be read.

    Raises:
        ConfigError: no corner-case database, or not a database.
    """
    db = run_dir / DB_NAME
    if not db.is_file():
        raise ConfigError(f"{run_dir}: no {DB_NAME} (the run recorded no corner cases, or is not a run folder)")
    try:
        raw = query_cases(db)
    except sqlite3.Error as err:
        raise ConfigError(f"{db}: not a corner-case database ({err})") from err
    rows, bad = [], []
    for r in raw:
        try:
            int(r["id"]), int(r["sim_time_ns"]), str(r["vehicle"]), str(r["kind"])
            r["params"] = json.loads(r["params"])
            r["event"] = json.loads(r["event"])
            rows.append(r)
        except (TypeError, ValueError, KeyError) as err:
            bad.append(f"case {r.get('id')!r}: unreadable row skipped ({type(err).__name__}: {err})")
    return rows, bad

"""Corner cases: each one a reference into the run's own recording, indexed.

``CaseRecorder`` stands in front of the run's ``Recorder`` (same methods): every
message goes to ``run.mcap`` unchanged, and the latest sim time of ``/ground_truth``
is noted. It subscribes to the run's event bus (:meth:`on_event`) and notes the
triggers: events whose kind is a trigger (every ``mismatch.*``, plus the
anomaly kinds named in config) — one event each, at most ``max_triggers``
of them (the rest counted in ``triggers_dropped`` and reported in ``errors``).
Nothing else is kept: no history, no images; memory is bounded whatever the run
length, and nothing is written to disk beside ``run.mcap`` until :meth:`close`.

At :meth:`close` the triggers become cases, grouped in **sim time**: triggers of
one vehicle, one kind and one cause (``perception``, ``latency``; none for timing
anomalies) whose sim times are at most ``after_s`` apart form one case (one lasting
mismatch, its escalations and its repeats are one case; a perception and a latency
mismatch never share one). Mismatch cases are numbered by first sim time, then
vehicle, kind and cause, and timing-anomaly cases after them in the same order: a
lockstep run gives the same mismatch cases, ids included, on any machine. A case's severity
is the highest of its events; its event (the one shown and replayed) is the first
at that severity. One row per case goes to ``corner_cases.sqlite`` (table
``cases``: run, scenario, seed, params, config hash, vehicle, sim time, kind,
cause, severity, summary, event, the number of events, and the window
``[first − history_s, last + after_s]`` in sim time), enough for ``hil replay`` to
re-run it. The window refers to ``run.mcap`` (``mcap_path``); after the run,
:func:`hil.harness.cases.windows.write_case_windows` can cut it out into
``corner_cases/case-NNNN.mcap`` (bounded in number).

An event without a sim time (clock-sync anomalies) takes the sim time of the
latest ``/ground_truth`` written before it.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.common.errors import ConfigError
from hil.harness.vocab.events import Event
from hil.harness.record.recorder import Recorder, RecorderStats

DB_NAME = "corner_cases.sqlite"
FOLDER = "corner_cases"
RUN_MCAP = "run.mcap"
MAX_TRIGGERS = 4096  # triggers noted per run (a few hundred bytes each): bounded memory
_RANK = {"info": 0, "warning": 1, "critical": 2}

SCHEMA = """
CREATE TABLE IF NOT EXISTS cases (
    id INTEGER PRIMARY KEY,
    run TEXT NOT NULL, scenario TEXT NOT NULL, seed INTEGER NOT NULL, params TEXT NOT NULL,
    config_hash TEXT NOT NULL, vehicle TEXT NOT NULL, sim_time_ns INTEGER NOT NULL,
    harness_time_ns INTEGER NOT NULL, kind TEXT NOT NULL, cause TEXT, severity TEXT,
    summary TEXT NOT NULL, event TEXT NOT NULL, mcap_path TEXT NOT NULL, messages INTEGER NOT NULL,
    events INTEGER NOT NULL DEFAULT 1, sim_end_ns INTEGER, window_start_ns INTEGER, window_end_ns INTEGER
)
"""


@dataclass(frozen=True)
class Trigger:
    """One event that opens or joins a case (times in ns)."""

    vehicle: str
    kind: str
    cause: str | None
    sim_time_ns: int
    harness_time_ns: int
    severity: str | None
    event: Mapping[str, Any]


@dataclass
class Case:
    """Triggers of one vehicle, kind and cause, each within ``after_s`` sim time of
    the previous one."""

    id: int
    triggers: list[Trigger]

    @property
    def first(self) -> Trigger:
        return self.triggers[0]

    @property
    def main(self) -> Trigger:
        """The first trigger at the case's highest severity."""
        return max(self.triggers, key=lambda t: _RANK.get(str(t.severity), -1))

    @property
    def sim_end_ns(self) -> int:
        return self.triggers[-1].sim_time_ns


def group_cases(triggers: list[Trigger], *, join_ns: int) -> list[Case]:
    """Cases from triggers, grouped and numbered in sim time (see the module
    docstring); the result does not depend on the order of ``triggers``."""
    by_key: dict[tuple[str, str, str], list[Trigger]] = {}
    for t in triggers:
        by_key.setdefault((t.vehicle, t.kind, t.cause or ""), []).append(t)
    groups: list[list[Trigger]] = []
    for ts in by_key.values():
        # Sim time, then what does not depend on the machine (never harness time).
        ts.sort(key=lambda t: (t.sim_time_ns, -_RANK.get(str(t.severity), -1), str(t.event.get("entity")),
                               str(t.event.get("detail"))))
        cur = [ts[0]]
        for t in ts[1:]:
            if t.sim_time_ns - cur[-1].sim_time_ns <= join_ns:
                cur.append(t)
            else:
                groups.append(cur)
                cur = [t]
        groups.append(cur)
    # Mismatch cases first: timing anomalies depend on the machine, their number must
    # not shift the ids of the cases that do not.
    groups.sort(key=lambda g: (not g[0].kind.startswith("mismatch."), g[0].sim_time_ns, g[0].vehicle, g[0].kind,
                               g[0].cause or ""))
    return [Case(i, g) for i, g in enumerate(groups, 1)]


class CaseRecorder:
    """A ``Recorder`` stand-in that also notes corner cases (see module docstring).

    ``history_s``/``after_s``: the window kept before the first and after the last
    trigger of a case, in sim time (s); ``after_s`` also joins triggers into a case.
    """

    def __init__(self, rec: Recorder, run_dir: Path, *, run_meta: Mapping[str, Any], history_s: float,
                 after_s: float, trigger_kinds: set[str], max_triggers: int = MAX_TRIGGERS) -> None:
        self.rec = rec
        self.run_dir = run_dir
        self.meta = dict(run_meta)
        self.history_ns = int(history_s * 1e9)
        self.after_ns = int(after_s * 1e9)
        self.triggers = set(trigger_kinds)
        self.max_triggers = max_triggers
        self._noted: list[Trigger] = []
        self._sim_ns = 0  # sim time of the latest /ground_truth written
        self.triggers_dropped = 0
        self.cases_written = 0
        self.errors: list[str] = []
        self.cases: list[Case] = []
        self._closed = False

    # -- Recorder interface ------------------------------------------------------

    def register_json_channel(self, topic: str, schema_name: str, schema: Mapping[str, Any]) -> None:
        self.rec.register_json_channel(topic, schema_name, schema)

    @property
    def failure(self) -> str | None:
        """The underlying recorder's write failure (e.g. the disk filled), or None."""
        return self.rec.failure

    def write_json(self, topic: str, obj: Mapping[str, Any], *, log_time_ns: int, publish_time_ns: int) -> bool:
        ok = self.rec.write_json(topic, obj, log_time_ns=log_time_ns, publish_time_ns=publish_time_ns)
        if topic == "/ground_truth":
            t = obj.get("sim_time_ns")
            if isinstance(t, int):
                self._sim_ns = max(self._sim_ns, t)
        return ok

    def write_image(self, topic: str, data: bytes, *, fmt: str, frame_id: str, log_time_ns: int,
                    publish_time_ns: int) -> bool:
        return self.rec.write_image(topic, data, fmt=fmt, frame_id=frame_id, log_time_ns=log_time_ns,
                                    publish_time_ns=publish_time_ns)

    def write_raw_image(self, topic: str, pixels: np.ndarray, *, encoding: str, frame_id: str, log_time_ns: int,
                        publish_time_ns: int) -> bool:
        return self.rec.write_raw_image(topic, pixels, encoding=encoding, frame_id=frame_id,
                                        log_time_ns=log_time_ns, publish_time_ns=publish_time_ns)

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        self.rec.add_metadata(name, data)

    def flush(self, **kw: Any) -> bool:
        return self.rec.flush(**kw)

    @property
    def stats(self) -> RecorderStats:
        return self.rec.stats

    # -- cases -------------------------------------------------------------------

    def on_event(self, ev: Event, log_time_ns: int) -> None:
        """A subscriber of the run's event bus: every mismatch, and the event kinds
        named in ``corner_cases.on_anomalies``, are noted as triggers."""
        if not (ev.kind.is_mismatch or ev.kind.value in self.triggers):
            return
        if len(self._noted) >= self.max_triggers:
            self.triggers_dropped += 1
            return
        sim = ev.sim_time_ns if ev.sim_time_ns is not None else self._sim_ns
        self._noted.append(Trigger(ev.vehicle or "", ev.kind.value, ev.cause, sim, log_time_ns, ev.severity.value,
                                   ev.to_json()))

    def close(self) -> None:
        """Group the triggers into cases and write their rows (idempotent). A case
        that cannot be written is an entry in ``errors``, never raised."""
        if self._closed:
            return
        self._closed = True
        if self.triggers_dropped:
            self.errors.append(f"{self.triggers_dropped} corner-case triggers beyond the first "
                               f"{self.max_triggers} were not noted")
        self.cases = group_cases(self._noted, join_ns=self.after_ns)
        self._noted = []
        if not self.cases:
            return
        db = self.run_dir / DB_NAME
        try:
            con = sqlite3.connect(db)
        except sqlite3.Error as err:
            self.errors.append(f"{db}: {err}")
            return
        try:
            con.execute(SCHEMA)
            for case in self.cases:
                try:
                    self._write_row(con, case)
                    con.commit()
                    self.cases_written += 1
                except Exception as err:  # noqa: BLE001 - any failure must reach the summary
                    self.errors.append(f"case {case.id}: {type(err).__name__}: {err}")
        except (sqlite3.Error, OSError) as err:  # e.g. the disk is full: said in the summary, never raised
            self.errors.append(f"{db}: {type(err).__name__}: {err}")
        finally:
            con.close()
        if not self.cases_written:
            db.unlink(missing_ok=True)  # no half-made (0-byte) database left behind

    def _write_row(self, con: sqlite3.Connection, case: Case) -> None:
        first, main = case.first, case.main
        n = len(case.triggers)
        summary = str(main.event.get("detail") or main.kind)
        if n > 1:
            summary += f" ({n} events over {(case.sim_end_ns - first.sim_time_ns) / 1e9:.2f} s of sim time)"
        con.execute(
            "INSERT INTO cases (id, run, scenario, seed, params, config_hash, vehicle, sim_time_ns, harness_time_ns,"
            " kind, cause, severity, summary, event, mcap_path, messages, events, sim_end_ns, window_start_ns,"
            " window_end_ns) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
            (case.id, str(self.meta.get("name")), str(self.meta.get("scenario")), int(self.meta.get("seed", 0)),
             json.dumps(self.meta.get("scenario_params", {}), sort_keys=True), str(self.meta.get("config_hash")),
             first.vehicle, first.sim_time_ns, first.harness_time_ns, first.kind, first.cause, main.severity,
             summary, json.dumps(main.event, default=str), RUN_MCAP, 0, n, case.sim_end_ns,
             max(0, first.sim_time_ns - self.history_ns), case.sim_end_ns + self.after_ns))


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

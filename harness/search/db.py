"""``CAMPAIGN/campaign.sqlite``: the campaign, its episodes and every corner case found.

Tables::

    campaign  (id, name, seed, episodes, strategy, spec, hil_version, created)   one row
    shards    (shard, source, started, finished, wall_s, episodes, host)         one per slice run
    episodes  (episode, shard, generation, origin, seed, params, unit, status, ended_by, error,
               sim_s, wall_s, virtual_km, cases, anomalies, mismatches, collisions, min_gap,
               score, trace_hash, dir)
    cases     (episode, case_id, vehicle, sim_time_ns, kind, cause, severity, summary, event,
               mcap_path, episode_dir)

``campaign.id`` is the resolved spec's hash; ``spec`` its JSON (self-contained: the
campaign can be resumed or re-run from it). ``cases.mcap_path`` is the window MCAP
relative to the campaign folder and ``episode_dir`` the run folder for
``hil replay EPISODE_DIR CASE_ID``.
"""

from __future__ import annotations

import json
import socket
import sqlite3
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Self

from hil.common.errors import ConfigError
from hil.harness import __version__
from hil.harness.search.episode import EpisodeResult
from hil.harness.search.spec import Campaign

DB_NAME = "campaign.sqlite"

SCHEMA = """
CREATE TABLE IF NOT EXISTS campaign (
    id TEXT PRIMARY KEY, name TEXT NOT NULL, seed INTEGER NOT NULL, episodes INTEGER NOT NULL,
    strategy TEXT NOT NULL, spec TEXT NOT NULL, hil_version TEXT NOT NULL, created TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS shards (
    shard TEXT NOT NULL, source TEXT NOT NULL, started TEXT, finished TEXT, wall_s REAL,
    episodes INTEGER, host TEXT
);
CREATE TABLE IF NOT EXISTS episodes (
    episode INTEGER PRIMARY KEY, shard TEXT NOT NULL, generation INTEGER NOT NULL, origin TEXT NOT NULL,
    seed INTEGER NOT NULL, params TEXT NOT NULL, unit TEXT NOT NULL, status TEXT NOT NULL, ended_by TEXT,
    error TEXT, sim_s REAL, wall_s REAL, virtual_km REAL, cases INTEGER, anomalies INTEGER,
    mismatches TEXT, collisions INTEGER, min_gap REAL, score REAL, trace_hash TEXT, dir TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS cases (
    episode INTEGER NOT NULL, case_id INTEGER NOT NULL, vehicle TEXT, sim_time_ns INTEGER, kind TEXT NOT NULL,
    cause TEXT, severity TEXT, summary TEXT, event TEXT, mcap_path TEXT NOT NULL, episode_dir TEXT NOT NULL,
    PRIMARY KEY (episode, case_id)
);
"""

EPISODE_COLS = ("episode", "shard", "generation", "origin", "seed", "params", "unit", "status", "ended_by", "error",
                "sim_s", "wall_s", "virtual_km", "cases", "anomalies", "mismatches", "collisions", "min_gap",
                "score", "trace_hash", "dir")
CASE_COLS = ("episode", "case_id", "vehicle", "sim_time_ns", "kind", "cause", "severity", "summary", "event",
             "mcap_path", "episode_dir")


def now_text() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


class CampaignDB:
    """The campaign database (a context manager; ``close`` is idempotent)."""

    def __init__(self, path: Path, *, readonly: bool = False) -> None:
        self.path = path
        try:
            if readonly:
                self.con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
            else:
                self.con = sqlite3.connect(path)
                self.con.executescript(SCHEMA)
            self.con.row_factory = sqlite3.Row
        except sqlite3.Error as err:
            raise ConfigError(f"{path}: not a campaign database ({err})") from err

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        con = getattr(self, "con", None)
        if con is not None:
            con.close()
            self.con = None  # type: ignore[assignment]  # closed: a later use fails at once

    # -- campaign ----------------------------------------------------------------------

    def init_campaign(self, c: Campaign) -> None:
        """Write the campaign row, or check it matches the one there.

        Raises:
            ConfigError: the database holds a different campaign.
        """
        have = self.campaign_row()
        if have is not None:
            if have["id"] != c.campaign_id:
                raise ConfigError(f"{self.path}: holds campaign {have['id']} ({have['name']}), not {c.campaign_id} "
                                  f"({c.name}): a different spec, seed, episode count or run config")
            return
        self.con.execute("INSERT INTO campaign VALUES (?,?,?,?,?,?,?,?)", (
            c.campaign_id, c.name, c.seed, c.episodes, c.strategy.kind.value,
            json.dumps(c.as_json(), sort_keys=True), __version__, now_text()))
        self.con.commit()

    def campaign_row(self) -> dict[str, Any] | None:
        try:
            row = self.con.execute("SELECT * FROM campaign").fetchone()
        except sqlite3.Error as err:
            raise ConfigError(f"{self.path}: not a campaign database ({err})") from err
        return None if row is None else dict(row)

    def campaign(self) -> Campaign:
        """The stored campaign. Raises ConfigError when there is none."""
        row = self.campaign_row()
        if row is None:
            raise ConfigError(f"{self.path}: no campaign recorded")
        return Campaign.from_json(json.loads(row["spec"]), source=str(self.path))

    # -- shards ------------------------------------------------------------------------

    def add_shard(self, shard: str, source: str, *, started: str, finished: str | None = None,
                  wall_s: float | None = None, episodes: int | None = None, host: str | None = None) -> int:
        cur = self.con.execute("INSERT INTO shards VALUES (?,?,?,?,?,?,?)",
                               (shard, source, started, finished, wall_s, episodes, host or socket.gethostname()))
        self.con.commit()
        return int(cur.lastrowid or 0)

    def finish_shard(self, rowid: int, *, wall_s: float, episodes: int) -> None:
        self.con.execute("UPDATE shards SET finished = ?, wall_s = ?, episodes = ? WHERE rowid = ?",
                         (now_text(), wall_s, episodes, rowid))
        self.con.commit()

    def shards(self) -> list[dict[str, Any]]:
        return [dict(r) for r in self.con.execute("SELECT * FROM shards ORDER BY rowid")]

    # -- episodes and cases ------------------------------------------------------------

    def put_episode(self, r: EpisodeResult) -> None:
        """Store (or replace: a re-run after ``--resume``) one episode and its cases."""
        row = (r.index, r.shard, r.generation, r.origin, r.seed, json.dumps(r.params, sort_keys=True),
               json.dumps(r.unit), r.status, r.ended_by, r.error, r.sim_s, r.wall_s, r.virtual_km, len(r.cases),
               r.anomalies, json.dumps(r.mismatches, sort_keys=True), r.collisions, r.min_gap_m, r.score,
               r.trace_hash, r.dir)
        with self.con:
            self.con.execute(f"INSERT OR REPLACE INTO episodes VALUES ({','.join('?' * len(EPISODE_COLS))})", row)
            self.con.execute("DELETE FROM cases WHERE episode = ?", (r.index,))
            self.con.executemany(f"INSERT INTO cases VALUES ({','.join('?' * len(CASE_COLS))})", [
                (r.index, int(c["id"]), c.get("vehicle"), c.get("sim_time_ns"), c["kind"], c.get("cause"),
                 c.get("severity"), c.get("summary"), json.dumps(c.get("event"), default=str),
                 f"{r.dir}/{c['mcap_path']}", r.dir) for c in r.cases])

    def insert_rows(self, table: str, rows: Iterable[dict[str, Any]]) -> None:
        """Copy rows read from another campaign database (a merge)."""
        cols = EPISODE_COLS if table == "episodes" else CASE_COLS
        with self.con:
            self.con.executemany(f"INSERT INTO {table} ({','.join(cols)}) VALUES ({','.join('?' * len(cols))})",
                                 [tuple(r[c] for c in cols) for r in rows])

    def episodes(self) -> list[dict[str, Any]]:
        """Every episode, by index, with JSON columns decoded."""
        out = []
        for r in self.con.execute("SELECT * FROM episodes ORDER BY episode"):
            d = dict(r)
            for k in ("params", "unit", "mismatches"):
                d[k] = json.loads(d[k]) if d[k] else ({} if k != "unit" else [])
            out.append(d)
        return out

    def raw_rows(self, table: str) -> list[dict[str, Any]]:
        order = "episode" if table == "episodes" else "episode, case_id"
        return [dict(r) for r in self.con.execute(f"SELECT * FROM {table} ORDER BY {order}")]

    def cases(self) -> list[dict[str, Any]]:
        return [dict(r) for r in self.con.execute("SELECT * FROM cases ORDER BY episode, case_id")]


def open_campaign_db(folder: Path) -> CampaignDB:
    """Read-only access to a campaign folder's database.

    Raises:
        ConfigError: no such folder, or no campaign database in it.
    """
    if not folder.is_dir():
        raise ConfigError(f"{folder}: no such campaign folder")
    db = folder / DB_NAME
    if not db.is_file():
        raise ConfigError(f"{folder}: not a campaign folder (no {DB_NAME})")
    return CampaignDB(db, readonly=True)


__all__ = ["CASE_COLS", "DB_NAME", "EPISODE_COLS", "CampaignDB", "open_campaign_db"]

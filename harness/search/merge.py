"""``hil search merge OUT SHARD_DIR...``: the shards of one campaign as one result.

Everything is checked before anything is written: each source is a campaign folder,
all hold the same campaign id (the same resolved spec), no episode appears twice,
and every episode's folder is there. ``OUT`` must not exist (or be an empty folder).
The merge is built in ``OUT.partial`` and renamed to ``OUT`` at the end, so a failed
merge leaves no half result. Episode folders are hard-linked where the filesystem
allows (same device), else copied; sources are never changed. A merged campaign
can itself be merged again (the shards of a shard's rerun, say).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil.common.errors import ConfigError
from hil.harness.search.db import DB_NAME, CampaignDB, open_campaign_db


@dataclass(frozen=True)
class MergeResult:
    out: Path
    episodes: int
    cases: int
    linked: bool
    summary: dict[str, Any]


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def merge(out: Path, sources: Sequence[Path]) -> MergeResult:
    """Merge campaign folders ``sources`` into ``out`` (see the module docstring).

    Raises:
        ConfigError: no sources, ``out`` exists and is not empty (or is a source),
            a source is not a campaign folder, the sources hold different campaigns,
            an episode is in two sources, or an episode folder is missing.
    """
    if not sources:
        raise ConfigError("hil search merge: give the shard folders to merge after OUT")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"{out}: exists already; merge writes a new folder and overwrites nothing")
    partial = out.with_name(out.name + ".partial")
    if partial.exists():
        raise ConfigError(f"{partial}: left by an earlier merge that failed; remove it first")
    resolved = [s.resolve() for s in sources]
    if len(set(resolved)) != len(resolved):
        raise ConfigError("hil search merge: a shard folder is listed twice")
    if out.resolve() in resolved:
        raise ConfigError(f"{out}: is one of the sources")
    loaded = []
    campaign_id = None
    first = None
    for src in sources:
        with open_campaign_db(src) as db:
            row = db.campaign_row()
            if row is None:
                raise ConfigError(f"{src}: {DB_NAME} holds no campaign")
            if campaign_id is None:
                campaign_id, first = row["id"], src
            elif row["id"] != campaign_id:
                raise ConfigError(f"{src}: campaign {row['id']} ({row['name']}) differs from {first}'s "
                                  f"{campaign_id}: only shards of one campaign (same spec, seed, episode count "
                                  "and run config) can be merged")
            loaded.append((src, row, db.raw_rows("episodes"), db.raw_rows("cases"), db.shards()))
    owner: dict[int, Path] = {}
    for src, _row, eps, _cases, _shards in loaded:
        for e in eps:
            i = int(e["episode"])
            if i in owner:
                raise ConfigError(f"episode {i} is in both {owner[i]} and {src}: merge each shard once "
                                  "(shards of one --shard i/N split are disjoint)")
            owner[i] = src
            if not (src / e["dir"]).is_dir():
                raise ConfigError(f"{src}: episode {i}'s folder {e['dir']} is missing")
    try:
        (partial / "episodes").mkdir(parents=True)
        linked = True
        with CampaignDB(partial / DB_NAME) as db:
            row0 = loaded[0][1]
            db.con.execute("INSERT INTO campaign VALUES (?,?,?,?,?,?,?,?)",
                           tuple(row0[k] for k in ("id", "name", "seed", "episodes", "strategy", "spec",
                                                   "hil_version", "created")))
            db.con.commit()
            for src, _row, eps, cases, shards in loaded:
                for s in shards:
                    db.add_shard(s["shard"], s["source"], started=s["started"], finished=s["finished"],
                                 wall_s=s["wall_s"], episodes=s["episodes"], host=s["host"])
                for e in eps:
                    shutil.copytree(src / e["dir"], partial / e["dir"], copy_function=_link_or_copy)
                    linked = linked and _same_device(src, partial)
                db.insert_rows("episodes", eps)
                db.insert_rows("cases", cases)
        if out.exists():
            out.rmdir()  # an empty folder (checked above)
        os.replace(partial, out)
    except OSError as err:
        shutil.rmtree(partial, ignore_errors=True)
        raise ConfigError(f"{out}: cannot write the merge: {err.strerror or err}") from err
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    from hil.harness.search.campaign_page import write_outputs

    summary = write_outputs(out)
    return MergeResult(out=out, episodes=len(owner), cases=sum(len(x[3]) for x in loaded), linked=linked,
                       summary=summary)


def _same_device(a: Path, b: Path) -> bool:
    try:
        return a.stat().st_dev == b.stat().st_dev
    except OSError:
        return False


__all__ = ["MergeResult", "merge"]

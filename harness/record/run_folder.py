"""Reading a run folder back: its ``summary.json`` and ``run.mcap``.

What ``hil report``, ``hil compare`` and the pytest plugin share. A run folder (see
``hil.harness.run.driver``) holds ``run.mcap`` and, when the run ended normally or was stopped
cleanly, ``summary.json``. A run killed outright leaves a truncated ``run.mcap`` and
no summary; :func:`read_run` still reads every complete chunk of it
(:func:`hil.harness.record.recorder.iter_salvaged_messages`) and says it was truncated.

Times are integer nanoseconds on the harness clock (``time.monotonic_ns``) unless
named otherwise.

Raises: :class:`hil.common.errors.ConfigError`, one line naming the path, for a path
that does not exist, a folder that is not a run, and a file that is not what its
name says (a text file named ``summary.json``, a truncated summary, a file named
``run.mcap`` that is not MCAP).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import struct
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import orjson

from hil.common.errors import ConfigError
from hil.harness.vocab.figures import RunFigures
from hil.timing.records import FrameStatus, PipelineRecord

SUMMARY_NAME = "summary.json"
MCAP_NAME = "run.mcap"
CONFIG_NAME = "config.json"
CORNER_DB_NAME = "corner_cases.sqlite"
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_VEHICLE_TOPIC = re.compile(r"^/(?P<vehicle>[^/]+)/(?P<what>pipeline|camera|clock_sync|clock)$")


def run_dir_of(path: str | os.PathLike[str]) -> Path:
    """The run folder that ``path`` names: the folder itself, or the folder of a
    ``run.mcap`` / ``summary.json`` path.

    Raises:
        ConfigError: ``path`` does not exist, or holds neither ``run.mcap`` nor
            ``summary.json`` (not a run folder).
    """
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{p}: no such file or folder")
    if p.is_file():
        if p.name in (MCAP_NAME, SUMMARY_NAME) or p.suffix == ".mcap":
            return p.parent
        raise ConfigError(f"{p}: not a run folder, run.mcap or summary.json")
    if not (p / MCAP_NAME).is_file() and not (p / SUMMARY_NAME).is_file():
        raise ConfigError(f"{p}: not a run folder (it has neither {MCAP_NAME} nor {SUMMARY_NAME})")
    return p


def summary_path_of(path: str | os.PathLike[str]) -> Path:
    """The ``summary.json`` that ``path`` names (a run folder or the file itself).

    Raises:
        ConfigError: missing path, a folder without ``summary.json``.
    """
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{p}: no such file or folder")
    if p.is_dir():
        s = p / SUMMARY_NAME
        if not s.is_file():
            why = (" (the run did not finish: only run.mcap; see hil report)"
                   if (p / MCAP_NAME).is_file() else " (not a run folder)")
            raise ConfigError(f"{p}: no {SUMMARY_NAME}{why}")
        return s
    return p


def load_summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read and check a ``summary.json`` (or the one in a run folder), as written.

    Raises:
        ConfigError: missing, unreadable, not JSON (truncated, binary, text), JSON
            that is not a run summary (no ``vehicles`` mapping), or a field of the
            wrong type (:meth:`hil.harness.vocab.figures.RunFigures.from_json` names it).
    """
    return _load(path)[0]


def load_figures(path: str | os.PathLike[str]) -> RunFigures:
    """A ``summary.json`` (or the one in a run folder) as the run's typed figures.

    Raises:
        ConfigError: as :func:`load_summary`.
    """
    return _load(path)[1]


def _load(path: str | os.PathLike[str]) -> tuple[dict[str, Any], RunFigures]:
    p = summary_path_of(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except OSError as err:
        raise ConfigError(f"{p}: cannot read: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        raise ConfigError(f"{p}: not a run summary: not UTF-8 text (byte offset {err.start})") from err
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        cut = err.pos >= len(text.rstrip()) - 1 or err.msg.startswith("Unterminated string")
        what = "truncated JSON" if cut and text.lstrip().startswith("{") else "invalid JSON"
        raise ConfigError(f"{p}: not a run summary: {what} at line {err.lineno} column {err.colno} "
                          f"({err.msg})") from err
    if not isinstance(data, dict) or not isinstance(data.get("vehicles"), dict):
        raise ConfigError(f"{p}: not a run summary: JSON without a 'vehicles' mapping")
    try:
        return data, RunFigures.from_json(data)
    except ConfigError as err:
        raise ConfigError(f"{p}: not a run summary: {err}") from err


@dataclass(frozen=True)
class RecordedEvent:
    """One ``/events`` message as read back from a run folder, any run's (also an older
    harness's, whose kinds may not be ours): ``kind`` as text, the message as ``data``.
    ``hil.harness.vocab.events.Event.from_json(data)`` gives the typed event where
    the kind is ours. ``t_ns``: its publish time (when it happened, harness clock);
    ``vehicles``: those it concerns (empty: the whole run)."""

    t_ns: int
    kind: str
    vehicles: tuple[str, ...]
    severity: Any
    data: dict[str, Any]


@dataclass(frozen=True)
class ClockPoint:
    """One clock-mapping sample of a vehicle's target clock: ``offset_ns`` (target −
    harness), ``uncertainty_ns`` (half the round trip, or the estimator's own),
    ``skew_ppm`` and its bound ``skew_uncertainty_ppm`` when the source gives them.
    ``t_ns``: harness time of the sample."""

    t_ns: int
    offset_ns: float
    uncertainty_ns: float
    skew_ppm: float | None
    skew_uncertainty_ppm: float | None = None


@dataclass
class RunData:
    """What a run folder holds, read back. ``pipeline``: per vehicle, the
    ``/V/pipeline`` records as written (dicts, file order); ``camera_times``: per
    vehicle, the publish times (``t0``) of its camera frames; ``clock`` per vehicle
    from ``/V/clock`` when present, else from ``/V/clock_sync``; ``clock_states``:
    every ``/V/clock`` message as written, as ``(t4, position, message)`` (the harness
    time of its sync sample; its index among the file's messages);
    ``pipeline_positions``: the same index of each ``pipeline`` record (the file's
    order is the order the run's analysis wrote them in); ``sync_exchanges``: every
    ``/V/clock_sync`` message as written. ``summary``: the run's ``summary.json`` as
    its typed figures (``None``: the run has none)."""

    run_dir: Path
    summary: RunFigures | None
    summary_problem: str | None
    meta: dict[str, Any]
    mcap_present: bool
    truncated: bool
    mcap_bytes: int
    messages: int
    pipeline: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    events: list[RecordedEvent] = field(default_factory=list)
    clock: dict[str, list[ClockPoint]] = field(default_factory=dict)
    clock_source: dict[str, str] = field(default_factory=dict)
    camera_times: dict[str, list[int]] = field(default_factory=dict)
    clock_states: dict[str, list[tuple[int, int, dict[str, Any]]]] = field(default_factory=dict)
    pipeline_positions: dict[str, list[int]] = field(default_factory=dict)
    sync_exchanges: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None

    @property
    def vehicles(self) -> list[str]:
        names = [] if self.summary is None else list(self.summary.vehicles)
        names += [v for v in sorted(set(self.pipeline) | set(self.camera_times)) if v not in names]
        return names

    @cached_property
    def t_start_ns(self) -> int:
        """Time zero of plots: the first capture ``t0``, else the first message (taken
        once, on the first use, from what was read: the report asks ~800 times at 64
        vehicles, and each look went over every vehicle's first records)."""
        t0s: list[int] = [r["t0_ns"] for recs in self.pipeline.values() for r in recs[:64] if "t0_ns" in r]
        if t0s:
            return min(t0s)
        return self.first_ns or 0


def is_finalized_mcap(path: Path) -> bool:
    """True when ``path`` ends with the MCAP closing magic (written by ``finish``)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            if size < 2 * len(_MCAP_MAGIC):
                return False
            f.seek(size - len(_MCAP_MAGIC))
            return f.read() == _MCAP_MAGIC
    except OSError:
        return False


def _event(t_ns: int, d: dict[str, Any]) -> RecordedEvent:
    who: list[str] = []
    for key in ("vehicle", "a", "b"):
        v = d.get(key)
        if isinstance(v, str) and v not in who:
            who.append(v)
    vs = d.get("vehicles")
    if isinstance(vs, list):
        who += [v for v in vs if isinstance(v, str) and v not in who]
    return RecordedEvent(t_ns, str(d.get("kind", "unknown")), tuple(who), d.get("severity"), d)


def _metadata(path: Path) -> dict[str, Any]:
    """The ``run`` metadata record of a finalized file, values JSON-decoded."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            for rec in make_reader(f).iter_metadata():
                if rec.name == "run":
                    out: dict[str, Any] = {}
                    for k, v in rec.metadata.items():
                        try:
                            out[k] = json.loads(v)
                        except ValueError:
                            out[k] = v
                    return out
    except (McapError, OSError, ValueError, KeyError, struct.error):
        return {}  # metadata is a nicety: a damaged summary section only loses it
    return {}


def read_run(path: str | os.PathLike[str]) -> RunData:
    """Read a run folder (or its ``run.mcap``/``summary.json``) for a report.

    A missing ``summary.json`` is not an error when ``run.mcap`` is there (a killed
    run); it shows in ``summary_problem``. A truncated ``run.mcap`` is read up to its
    last complete chunk and sets ``truncated``.

    Raises:
        ConfigError: not a run folder, a ``summary.json`` that is not a summary, or
            a ``run.mcap`` that is not MCAP.
    """
    from hil.harness.record.recorder import iter_salvaged_messages

    run_dir = run_dir_of(path)
    mcap_path = run_dir / MCAP_NAME
    summary: RunFigures | None = None
    problem: str | None = None
    if (run_dir / SUMMARY_NAME).is_file():
        summary = load_figures(run_dir / SUMMARY_NAME)
    else:
        problem = f"no {SUMMARY_NAME} (the run did not finish normally)"
    data = RunData(run_dir=run_dir, summary=summary, summary_problem=problem, meta={},
                   mcap_present=mcap_path.is_file(), truncated=False, mcap_bytes=0, messages=0)
    if not data.mcap_present:
        return data
    data.mcap_bytes = mcap_path.stat().st_size
    pipeline: dict[str, list[dict[str, Any]]] = defaultdict(list)
    sync: dict[str, list[ClockPoint]] = defaultdict(list)
    clock: dict[str, list[ClockPoint]] = defaultdict(list)
    cams: dict[str, list[int]] = defaultdict(list)
    states: dict[str, list[tuple[int, int, dict[str, Any]]]] = defaultdict(list)
    positions: dict[str, list[int]] = defaultdict(list)
    exchanges: dict[str, list[dict[str, Any]]] = defaultdict(list)
    first = last = None
    n = 0
    offset: int | None = None  # log_time - monotonic (the recorder's time anchor; 0 in old runs)
    for _schema, channel, msg in iter_salvaged_messages(mcap_path):
        n += 1
        t = msg.log_time
        if offset is None and channel.topic == "/ground_truth":
            offset = msg.log_time - msg.publish_time  # written with log == publish time
        first = t if first is None or t < first else first
        last = t if last is None or t > last else last
        topic = channel.topic
        if topic == "/events":
            d = _json(msg.data)
            if isinstance(d, dict):
                data.events.append(_event(msg.publish_time, d))
            continue
        m = _VEHICLE_TOPIC.match(topic)
        if m is None:
            continue
        vehicle, what = m["vehicle"], m["what"]
        if what == "camera":
            cams[vehicle].append(msg.publish_time)
            continue
        d = _json(msg.data)
        if not isinstance(d, dict):
            continue
        if what == "pipeline":
            pipeline[vehicle].append(d)
            positions[vehicle].append(n - 1)
            continue
        if what == "clock_sync":
            exchanges[vehicle].append(d)
        else:
            states[vehicle].append((msg.log_time, n - 1, d))
        if what == "clock_sync" and _num(d, "offset_ns") and _num(d, "delay_ns"):
            sync[vehicle].append(ClockPoint(msg.log_time, float(d["offset_ns"]), d["delay_ns"] / 2, None))
        elif what == "clock" and _num(d, "offset_ns"):
            clock[vehicle].append(ClockPoint(msg.log_time, float(d["offset_ns"]),
                                             float(d["uncertainty_ns"]) if _num(d, "uncertainty_ns") else 0.0,
                                             float(d["skew_ppm"]) if _num(d, "skew_ppm") else None,
                                             float(d["skew_uncertainty_ppm"]) if _num(d, "skew_uncertainty_ppm")
                                             else None))
    off = offset or 0
    if off:
        first = None if first is None else first - off
        last = None if last is None else last - off
        for points in (*sync.values(), *clock.values()):
            points[:] = [replace(p, t_ns=p.t_ns - off) for p in points]
        for v, vs in states.items():
            states[v] = [(t - off, i, d) for t, i, d in vs]
    data.messages, data.first_ns, data.last_ns = n, first, last
    data.truncated = not is_finalized_mcap(mcap_path)
    if n == 0 and data.truncated and data.mcap_bytes < 64 and summary is None:
        # A few bytes of magic and nothing else: nothing to report on.
        raise ConfigError(f"{mcap_path}: truncated MCAP with no complete message ({data.mcap_bytes} bytes)")
    data.pipeline = dict(pipeline)
    data.camera_times = {v: sorted(ts) for v, ts in cams.items()}
    data.clock_states, data.pipeline_positions, data.sync_exchanges = dict(states), dict(positions), dict(exchanges)
    for v in set(sync) | set(clock):
        if clock.get(v):
            data.clock[v], data.clock_source[v] = clock[v], f"/{v}/clock"
        else:
            data.clock[v], data.clock_source[v] = sync[v], f"/{v}/clock_sync"
    if not data.truncated:
        data.meta = _metadata(mcap_path)
    if not data.meta:
        data.meta = meta_from_config(run_dir)
    return data


def meta_from_config(run_dir: Path) -> dict[str, Any]:
    """What ran, from ``RUN/config.json`` (written before the run starts, so a killed
    run has it while its ``run.mcap`` has no metadata): ``name``, ``scenario``,
    ``scenario_params`` (as configured, defaults not filled in), ``seed`` and
    ``config_hash`` (the digest ``hil run`` records: ``hil.harness.config.digest``),
    with ``meta_source`` naming the file. Empty when it is missing or not a config."""
    from hil.harness.config.digest import digest

    try:
        cfg = json.loads((run_dir / CONFIG_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    if not isinstance(cfg, dict):
        return {}
    scenario = cfg.get("scenario")
    if not isinstance(scenario, dict):
        scenario = {}
    out = {"name": cfg.get("name"), "scenario": scenario.get("name"), "scenario_params": scenario.get("params"),
           "seed": cfg.get("seed"),
           "config_hash": digest(cfg)}
    return {**{k: v for k, v in out.items() if v is not None}, "meta_source": CONFIG_NAME}


def camera_images(mcap_path: Path, wanted: Iterable[tuple[str, int]]) -> dict[tuple[str, int], tuple[str, str]]:
    """The camera messages ``(vehicle, publish_time_ns)`` of ``wanted`` as
    ``(format, base64 data)``; missing ones are left out. Reads truncated files too.

    Raises:
        ConfigError: the file cannot be opened or is not MCAP.
    """
    from hil.harness.record.recorder import iter_salvaged_messages

    want = set(wanted)
    topics = {f"/{v}/camera" for v, _ in want}
    out: dict[tuple[str, int], tuple[str, str]] = {}
    if not want:
        return out
    for _schema, channel, msg in iter_salvaged_messages(mcap_path):
        if channel.topic not in topics:
            continue
        key = (channel.topic[1:-len("/camera")], msg.publish_time)
        if key in want:
            d = _json(msg.data)
            img = _as_compressed(d) if isinstance(d, dict) else None
            if img is not None:
                out[key] = img
                if len(out) == len(want):
                    break
    return out


def _as_compressed(d: dict[str, Any]) -> tuple[str, str] | None:
    """A Foxglove image message as ``(format, base64)``; a ``RawImage`` (rgb8/bgr8)
    is JPEG-encoded first. ``None`` when it cannot be read."""
    blob = d.get("data")
    if not isinstance(blob, str):
        return None
    if "format" in d:
        return str(d["format"]), blob
    import base64

    import cv2
    import numpy as np

    try:
        w, h, enc = int(d["width"]), int(d["height"]), str(d["encoding"])
        px = np.frombuffer(base64.b64decode(blob), np.uint8).reshape(h, w, 3)
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(px, cv2.COLOR_RGB2BGR) if enc == "rgb8" else px,
                               (cv2.IMWRITE_JPEG_QUALITY, 80))
    except (KeyError, TypeError, ValueError, cv2.error):
        return None
    return ("jpeg", base64.b64encode(buf.tobytes()).decode()) if ok else None


_RECORD_FIELDS = {f.name for f in dataclasses.fields(PipelineRecord)}


def pipeline_record(d: Any) -> PipelineRecord | None:
    """A ``/V/pipeline`` message as a :class:`hil.timing.records.PipelineRecord`
    (fields it does not know are left out); ``None`` when it is not one."""
    if not isinstance(d, dict):
        return None
    try:
        kw = {k: v for k, v in d.items() if k in _RECORD_FIELDS}
        kw["status"] = FrameStatus(str(d["status"]))
        return PipelineRecord(**kw)
    except (KeyError, TypeError, ValueError):
        return None


def _json(data: bytes) -> Any:
    """A message's JSON (None where it is not JSON): orjson first (faster over a run's
    messages; the recording writes with it), the standard library where orjson refuses
    what it accepts (the NaN or Infinity of recordings made before orjson wrote them)."""
    try:
        return orjson.loads(data)
    except ValueError:
        pass
    try:
        return json.loads(data)
    except ValueError:
        return None


def _num(d: dict[str, Any], key: str) -> bool:
    v = d.get(key)
    return isinstance(v, (int, float)) and not isinstance(v, bool)


__all__ = ["CONFIG_NAME", "ClockPoint", "RecordedEvent", "RunData", "camera_images", "is_finalized_mcap",
           "load_figures", "load_summary", "meta_from_config", "pipeline_record", "read_run", "run_dir_of",
           "summary_path_of"]

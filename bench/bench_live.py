"""Live-view benchmark: does ``hil run --live`` (with a viewer subscribed to every
channel) change the run?

Runs the same config ``--repeat`` times without and with ``--live``, alternating;
with ``--live`` a WebSocket client (the ``websockets`` package, standing in for
Foxglove) connects to the printed address and subscribes to every channel as it is
advertised, and counts what it receives. Prints per run: late physics steps, max
lateness, frames dropped, recorder drops, live-view messages sent/dropped, and
what the viewer received.

    .venv/bin/python bench/bench_live.py [--config hil_configs/demo.yaml] [--repeat 2] [--set K=V ...]

Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def _viewer(url: str, got: dict[str, int], stop: threading.Event) -> None:
    from websockets.sync.client import connect

    with connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
        next_id = 1
        while not stop.is_set():
            try:
                m = ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            except Exception:
                return  # the server stopped at the end of the run
            if isinstance(m, bytes):
                got["messages"] += 1
                got["bytes"] += len(m)
                continue
            d = json.loads(m)
            if d.get("op") == "advertise":
                subs = [{"id": next_id + i, "channelId": c["id"]} for i, c in enumerate(d["channels"])]
                next_id += len(subs)
                ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                got["channels"] += len(subs)


def one_run(config: str, sets: list[str], *, live: bool, folder: Path) -> dict[str, Any]:
    out = folder / ("live" if live else "plain")
    cmd = [sys.executable, "-m", "hil.harness.cli.main", "run", config, "--no-progress", "--out", str(out)]
    for s in sets:
        cmd += ["--set", s]
    if live:
        cmd.append("--live")
    got = {"messages": 0, "bytes": 0, "channels": 0}
    stop = threading.Event()
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    viewer = None
    assert p.stderr is not None
    err_lines = []
    for line in p.stderr:
        err_lines.append(line)
        m = re.search(r"live view: (ws://\S+)", line)
        if m and viewer is None:
            viewer = threading.Thread(target=_viewer, args=(m.group(1), got, stop), daemon=True)
            viewer.start()
    p.wait()
    stop.set()
    if viewer is not None:
        viewer.join(5)
    if p.returncode != 0:
        raise SystemExit(f"run failed ({p.returncode}): {''.join(err_lines)[-2000:]}")
    s = json.loads((out / "summary.json").read_text())
    rt = s["realtime"]
    from mcap.reader import make_reader

    with open(out / "run.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    lv = meta.get("live_view", {})
    return {"late_steps": rt.get("late_steps"), "max_lateness_ms": rt.get("max_lateness_ms"),
            "p999_ms": (rt.get("lateness_ms") or {}).get("p999"),
            "dropped": sum(v.get("dropped", 0) for v in s["vehicles"].values()),
            "frames": sum(v.get("frames_sent", 0) for v in s["vehicles"].values()),
            "rec_dropped": s["recorder"]["dropped"],
            "analysis_us": (s.get("harness_cost") or {}).get("analysis_thread_us_per_frame"),
            "live_sent": lv.get("sent", "–"), "live_dropped": lv.get("dropped", "–"), **got}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="hil_configs/demo.yaml")
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--set", dest="sets", action="append", default=[])
    a = p.parse_args(argv)
    print(f"config {a.config} {' '.join(a.sets)}\n")
    print("| run | frames | dropped frames | late steps | max lateness (ms) | p99.9 lateness (ms) | recorder drops "
          "| analysis µs/frame | live sent / dropped | viewer got (msgs, MB, channels) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(a.repeat):
            for live in (False, True):
                r = one_run(a.config, a.sets, live=live, folder=Path(tmp) / str(i))
                viewer = (f"{r['messages']}, {r['bytes'] / 1e6:.1f}, {r['channels']}" if live else "–")
                print(f"| {'live' if live else 'plain'} {i + 1} | {r['frames']} | {r['dropped']} | {r['late_steps']} | "
                      f"{r['max_lateness_ms']} | {r['p999_ms']} | {r['rec_dropped']} | {r['analysis_us']} | "
                      f"{r['live_sent']} / {r['live_dropped']} | {viewer} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

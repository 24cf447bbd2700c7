"""Pages as a person sees them: headless Chromium loads a page with a probe script
injected into a copy (the pages themselves hold no script) and reports, once loaded,
the script errors, every chart's size and every text in a chart that covers the plot
area (the data) or another text, every picture's state, and the page width.

Used by the run report's, the study report's (and any page's) browser tests."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(CHROMIUM is None,
                                    reason="no chromium: `make test` installs it where apt-get works")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-extensions", "--no-first-run", "--hide-scrollbars", "--mute-audio",
                 "--enable-logging=stderr", "--v=0"]
_PROBE = """<script>
window.__errors = [];
window.addEventListener('error', e => window.__errors.push(String(e.message || e.type)), true);
window.addEventListener('load', () => {
  const box = el => { const r = el.getBoundingClientRect(); return [r.width, r.height]; };
  const cut = (a, b) => Math.max(0, Math.min(a.right, b.right) - Math.max(a.left, b.left))
                      * Math.max(0, Math.min(a.bottom, b.bottom) - Math.max(a.top, b.top));
  const chart = svg => {
    const plot = svg.querySelector('rect[fill="#fafafa"]');
    const pr = plot ? plot.getBoundingClientRect() : null;
    const texts = [...svg.querySelectorAll('text')].map(t => ({s: t.textContent, r: t.getBoundingClientRect()}))
                                                   .filter(t => t.r.width > 0);
    const overlaps = [], over_plot = [];
    texts.forEach((a, i) => {
      if (pr && cut(a.r, pr) > 1) over_plot.push(a.s);
      texts.slice(i + 1).forEach(b => { if (cut(a.r, b.r) > 1) overlaps.push([a.s, b.s]); });
    });
    return {label: svg.getAttribute('aria-label'), box: box(svg), overlaps, over_plot};
  };
  const out = {errors: window.__errors, svgs: [...document.querySelectorAll('svg')].map(chart),
    imgs: [...document.querySelectorAll('img')].map(i => ({src: i.getAttribute('src').slice(0, 80), box: box(i),
                                                           natural: [i.naturalWidth, i.naturalHeight],
                                                           complete: i.complete})),
    width: document.documentElement.scrollWidth, viewport: window.innerWidth};
  document.body.setAttribute('data-probe', btoa(unescape(encodeURIComponent(JSON.stringify(out)))));
});
</script>"""


def chromium(args: list[str], url: str) -> subprocess.CompletedProcess[str]:
    """Run headless Chromium on ``url`` with ``args`` (e.g. ``--dump-dom``)."""
    assert CHROMIUM is not None
    return subprocess.run([CHROMIUM, *CHROMIUM_ARGS, *args, url], capture_output=True, text=True, timeout=90,
                          check=False, env={**os.environ, "HOME": os.environ.get("TMPDIR", "/tmp")})


def probe(page: Path, scratch: Path, *, window: str = "1200,900") -> dict[str, Any]:
    """Load a copy of ``page`` (in its own folder, so its relative links hold) with the
    probe, and return what it measured; asserts there was no script or console error."""
    probed = page.parent / f".probe-{scratch.name}-{page.name}"
    probed.write_text(page.read_text(encoding="utf-8").replace("<head>", "<head>" + _PROBE, 1), encoding="utf-8")
    try:
        p = chromium([f"--window-size={window}", "--virtual-time-budget=10000", "--dump-dom"], probed.as_uri())
    finally:
        probed.unlink()
    m = re.search(r'data-probe="([^"]+)"', p.stdout)
    assert m, p.stderr[-2000:]
    got: dict[str, Any] = json.loads(base64.b64decode(m.group(1)).decode("utf-8"))
    assert got["errors"] == []
    console = [ln for ln in p.stderr.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]
    assert console == [], console
    return got


def assert_charts_legible(got: dict[str, Any], *, at_least: int) -> None:
    """Every chart has a size, no text covers its plot area or another text, and the
    page fits the window (charts shrink, nothing overflows)."""
    assert len(got["svgs"]) >= at_least, len(got["svgs"])
    for svg in got["svgs"]:
        w, h = svg["box"]
        assert w > 50 and h > 30, svg
        assert svg["over_plot"] == [], (svg["label"], svg["over_plot"])
        assert svg["overlaps"] == [], (svg["label"], svg["overlaps"])
    assert got["width"] <= got["viewport"], (got["width"], got["viewport"])


__all__ = ["CHROMIUM", "assert_charts_legible", "chromium", "needs_chromium", "probe"]

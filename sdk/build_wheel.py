"""Build the ``hil-target-sdk`` wheel: the target side of the harness, for a device.

    python sdk/build_wheel.py [--out dist/]

The wheel holds the packages ``adapters`` (wire codec, stream decoder, the SDK's
``Endpoint``/``serve``/``decode_image``, every transport's target endpoint),
``timing`` (clocks, the clock-sync estimator) and ``hil_errors`` (the exception
tree), from this repository's own files: there is one copy of the code. It
depends on numpy only; extras add a transport's library (``zenoh``, ``can``) or
JPEG decoding (``jpeg``). Written with the standard library (a wheel is a zip
file with three metadata files, PEP 427), so it builds offline with no build
backend.

Exit 0 with the wheel's path on stdout; 2 with one line on stderr for a bad option.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NAME = "hil-target-sdk"
PACKAGES = ("adapters", "timing", "hil_errors")
DATA_SUFFIXES = (".py", ".dbc")
REQUIRES = ["numpy>=1.26,<2.5"]
EXTRAS = {
    "zenoh": ["eclipse-zenoh==1.10.2"],
    "can": ["python-can>=4.6,<5", "cantools>=39", "can-isotp>=2.0"],
    "jpeg": ["opencv-python-headless>=4.9"],
}
SUMMARY = "Target SDK of the HIL timing harness: serve an AI's infer(frame) over local, tcp, zenoh or CAN"


def version() -> str:
    """The harness's version (pyproject.toml): both distributions move together."""
    with open(ROOT / "pyproject.toml", "rb") as f:
        return str(tomllib.load(f)["project"]["version"])


def files() -> list[Path]:
    """The packaged files, relative to the repository root, in a stable order."""
    out = []
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*")):
            if p.is_file() and p.suffix in DATA_SUFFIXES and "__pycache__" not in p.parts:
                out.append(p.relative_to(ROOT))
    return out


def metadata(ver: str) -> str:
    lines = ["Metadata-Version: 2.1", f"Name: {NAME}", f"Version: {ver}", f"Summary: {SUMMARY}",
             "Requires-Python: >=3.11"]
    lines += [f"Requires-Dist: {r}" for r in REQUIRES]
    for extra, reqs in EXTRAS.items():
        lines.append(f"Provides-Extra: {extra}")
        lines += [f'Requires-Dist: {r}; extra == "{extra}"' for r in reqs]
    lines.append("Description-Content-Type: text/markdown")
    return "\n".join(lines) + "\n\n" + (ROOT / "sdk" / "README.md").read_text(encoding="utf-8")


def _record_line(name: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}"


def build(out_dir: Path) -> Path:
    """Write the wheel into ``out_dir`` (created); returns its path."""
    ver = version()
    dist_info = f"{NAME.replace('-', '_')}-{ver}.dist-info"
    wheel = out_dir / f"{NAME.replace('-', '_')}-{ver}-py3-none-any.whl"
    out_dir.mkdir(parents=True, exist_ok=True)
    entries: list[tuple[str, bytes]] = [(p.as_posix(), (ROOT / p).read_bytes()) for p in files()]
    entries += [
        (f"{dist_info}/METADATA", metadata(ver).encode()),
        (f"{dist_info}/WHEEL", b"Wheel-Version: 1.0\nGenerator: sdk/build_wheel.py\nRoot-Is-Purelib: true\n"
                               b"Tag: py3-none-any\n"),
        (f"{dist_info}/top_level.txt", ("\n".join(PACKAGES) + "\n").encode()),
    ]
    record = "\n".join(_record_line(n, d) for n, d in entries) + f"\n{dist_info}/RECORD,,\n"
    with zipfile.ZipFile(wheel, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, data in [*entries, (f"{dist_info}/RECORD", record.encode())]:
            info = zipfile.ZipInfo(name, date_time=(2026, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, data)
    return wheel


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python sdk/build_wheel.py", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "dist", help="folder for the wheel (default dist/)")
    a = p.parse_args(argv)
    if a.out.exists() and not a.out.is_dir():
        print(f"build_wheel: error: --out {a.out} is a file, not a folder", file=sys.stderr)
        return 2
    print(build(a.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Build the ``hil-target-sdk`` wheel: the target side of the harness, for a device.

    python sdk/build_wheel.py [--out dist/]

What goes in it is ``sdk/pyproject.toml`` (the same file ``pip install -e ./sdk``
reads), its ``packages`` and their ``package-data``: ``hil.adapters`` and its
subpackages (the wire codec, the SDK's ``Endpoint``/``serve``/``decode_image``, every
transport's package with its target endpoint, ``hil.dbc``, the ROS 2 ``.msg`` files),
``hil.timing`` (clocks, the clock-sync estimator) and ``hil.common`` (the exception
tree, object classes), from this repository's own folders: there is one copy of the
code. It depends on numpy only; extras add a transport's library (``zenoh``,
``can``) or JPEG decoding (``jpeg``). Written with the standard library (a wheel is
a zip file with three metadata files, PEP 427), so it builds offline with no build
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
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def project() -> dict[str, Any]:
    """sdk/pyproject.toml: the one definition of the distribution."""
    with open(ROOT / "sdk" / "pyproject.toml", "rb") as f:
        return tomllib.load(f)


def package_folder(pkg: str, package_dir: dict[str, str]) -> Path:
    """The folder of package ``pkg``, as setuptools resolves it: the longest prefix in
    ``package-dir`` (``hil.adapters.tcp`` -> ``adapters/tcp``)."""
    base = max((p for p in package_dir if pkg == p or pkg.startswith(p + ".")), key=len)
    rest = pkg.removeprefix(base).lstrip(".").split(".") if pkg != base else []
    return (ROOT / "sdk" / package_dir[base]).resolve().joinpath(*rest)


def files(setuptools: dict[str, Any]) -> list[tuple[str, Path]]:
    """``(name in the wheel, file)`` of every packaged file, in a stable order: each
    listed package's modules (``hil/adapters/sdk.py`` from ``adapters/sdk.py``; a
    package not listed is not shipped, as with setuptools) and its ``package-data``."""
    package_dir, data = setuptools["package-dir"], setuptools.get("package-data", {})
    out: dict[str, Path] = {}
    for pkg in sorted(setuptools["packages"]):
        src = package_folder(pkg, package_dir)
        found = list(src.glob("*.py")) + [p for pattern in data.get(pkg, []) for p in src.glob(pattern)]
        for p in found:
            if p.is_file() and "__pycache__" not in p.parts:
                out["/".join([*pkg.split("."), *p.relative_to(src).parts])] = p
    return sorted(out.items())


def metadata(proj: dict[str, Any]) -> str:
    lines = ["Metadata-Version: 2.1", f"Name: {proj['name']}", f"Version: {proj['version']}",
             f"Summary: {proj['description']}", f"Requires-Python: {proj['requires-python']}"]
    lines += [f"Requires-Dist: {r}" for r in proj["dependencies"]]
    for extra, reqs in proj["optional-dependencies"].items():
        lines.append(f"Provides-Extra: {extra}")
        lines += [f'Requires-Dist: {r}; extra == "{extra}"' for r in reqs]
    lines.append("Description-Content-Type: text/markdown")
    return "\n".join(lines) + "\n\n" + (ROOT / "sdk" / proj["readme"]).read_text(encoding="utf-8")


def _record_line(name: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}"


def build(out_dir: Path) -> Path:
    """Write the wheel into ``out_dir`` (created); returns its path."""
    conf = project()
    proj = conf["project"]
    stem = f"{proj['name'].replace('-', '_')}-{proj['version']}"
    dist_info = f"{stem}.dist-info"
    wheel = out_dir / f"{stem}-py3-none-any.whl"
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = [(name, p.read_bytes()) for name, p in files(conf["tool"]["setuptools"])]
    entries += [
        (f"{dist_info}/METADATA", metadata(proj).encode()),
        (f"{dist_info}/WHEEL", b"Wheel-Version: 1.0\nGenerator: sdk/build_wheel.py\nRoot-Is-Purelib: true\n"
                               b"Tag: py3-none-any\n"),
        (f"{dist_info}/top_level.txt", b"hil\n"),
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

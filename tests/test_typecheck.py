"""What ``make test``'s type check covers: every package the product installs (setup.py's
and the target SDK's, sdk/pyproject.toml), strict everywhere (pyproject.toml's
``[tool.mypy]``), no module of ours let off errors or imports, no library's errors
hidden whole. The check itself is ``tools/typecheck.py``, run by ``make test``."""

from __future__ import annotations

import ast
import importlib.util
import tomllib
from pathlib import Path
from types import ModuleType
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def _typecheck_tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("hil_typecheck_tool", ROOT / "tools" / "typecheck.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _installed_folders() -> set[str]:
    """The top-level folders the two distributions install as ``hil.<folder>``."""
    tree = ast.parse((ROOT / "setup.py").read_text(encoding="utf-8"))
    folders = next(ast.literal_eval(n.value) for n in ast.walk(tree) if isinstance(n, ast.Assign)
                   and any(isinstance(t, ast.Name) and t.id == "FOLDERS" for t in n.targets))
    sdk = tomllib.loads((ROOT / "sdk" / "pyproject.toml").read_text(encoding="utf-8"))
    return set(folders) | {p.removeprefix("hil.").split(".")[0] for p in sdk["tool"]["setuptools"]["packages"]}


def _mypy() -> dict[str, Any]:
    mypy: dict[str, Any] = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["mypy"]
    return mypy


def _ours(module: str) -> bool:
    return module == "hil" or module.startswith("hil.")


def test_every_installed_package_is_checked() -> None:
    cmd = _typecheck_tool().mypy_command()
    assert {a.removeprefix("hil/") for a in cmd if a.startswith("hil/")} == _installed_folders()


def test_strict_for_every_module_of_ours() -> None:
    mypy = _mypy()
    assert mypy.get("strict") is True
    # What an override may do to a module of ours: leave named error codes unreported
    # (the temporary block of files changed in another branch), nothing broader.
    allowed = {"module", "disable_error_code", "warn_unused_ignores"}
    for ov in mypy.get("overrides", []):
        modules = [ov["module"]] if isinstance(ov["module"], str) else ov["module"]
        assert "ignore_errors" not in ov, f"{modules}: ignore_errors hides every error; disable named codes"
        ours = [m for m in modules if _ours(m)]
        if ours:
            assert set(ov) <= allowed, f"{ours}: {sorted(set(ov) - allowed)} loosens the strict check"
        if ov.get("ignore_missing_imports"):
            assert not ours, f"{ours}: our own modules always resolve"

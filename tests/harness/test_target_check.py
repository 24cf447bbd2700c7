"""``hil target-check``: the scripted conformance session against the C reference
target (local and tcp), the Python cv target, and a target with a broken clock."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from hil.harness.cli import main as cli

from hil.harness.check import target_check
from tests.adapters.pair_tcp import tcp_echo
from tests.adapters.pair_zenoh import free_port
from tests.targets import c_build

needs_cc = pytest.mark.skipif(c_build.unavailable() is not None, reason=str(c_build.unavailable()))


def _rows(out: str) -> dict[str, str]:
    """check name -> PASS/FAIL, from the printed table."""
    rows = {}
    for line in out.splitlines()[1:-1]:
        name, _, rest = line.partition("  §")
        rows[name.strip()] = "PASS" if "  PASS  " in rest else "FAIL"
    return rows


@needs_cc
@pytest.mark.parametrize("clock", ["monotonic", "realtime"])
def test_c_target_passes_over_local(clock, capsys, monkeypatch):
    for k, v in c_build.SAN_ENV.items():
        monkeypatch.setenv(k, v)
    code = target_check.main(["local", "--", str(c_build.build().asan), "--clock", clock])
    out = capsys.readouterr().out
    assert code == 0, out
    rows = _rows(out)
    assert len(rows) == 13 and set(rows.values()) == {"PASS"}, out
    assert "command 'status'" in rows and "13 of 13 checks passed" in out
    assert f"clock {clock.upper()}" in out  # its own clock: the frame checks map it through clock sync


@needs_cc
def test_c_target_passes_over_tcp(capsys, tmp_path):
    address = f"127.0.0.1:{free_port()}"
    log = tmp_path / "c.log"
    with open(log, "ab") as f:
        proc = subprocess.Popen([str(c_build.build().asan), "--transport", "tcp", "--listen", address],
                                stdout=f, stderr=f, env=dict(os.environ, **c_build.SAN_ENV))
    try:
        code = target_check.main([f"tcp://{address}"])
        out = capsys.readouterr().out
        assert code == 0, out
        assert proc.wait(timeout=10) == 0  # it left on the checker's BYE
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert c_build.sanitizer_report(log.read_text()) is None, log.read_text()


@pytest.mark.slow
def test_python_cv_target_passes(capsys):
    # Before the SDK answered a bad version with UNSUPPORTED_VERSION (PROTOCOL.md
    # section 9) this failed on "unsupported version".
    code = target_check.main(["local", "--", sys.executable, "-m", "hil.targets.cv_baseline"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert _rows(out)["unsupported version"] == "PASS"


def test_broken_clock_fails_with_the_offsets(capsys, tmp_path):
    address = f"127.0.0.1:{free_port()}"
    with tcp_echo(tmp_path / "t.log", ["--bad-stamps", "backwards"], listen=address):
        code = target_check.main([f"tcp://{address}", "--timeout", "3"])
    out = capsys.readouterr().out
    assert code == 1, out
    rows = _rows(out)
    assert rows["frame RGB8 -> estimate"] == "FAIL"
    assert "t_rx (offset 24) is after t_infer_start (offset 32)" in out
    assert rows["clock sync burst"] == "FAIL" and "t2 (offset 32) is after t3 (offset 40)" in out
    assert rows["bye ends the session"] == "PASS"


@pytest.mark.parametrize("argv, message", [
    (["bogus"], "ENDPOINT 'bogus'"), (["tcp://nohost"], "ENDPOINT='nohost'"),
    (["local"], "give the target's command after --"), (["can://socketcan"], "can://INTERFACE/CHANNEL"),
    (["tcp://127.0.0.1:1", "--timeout", "0"], "--timeout must be > 0"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert cli.main(["target-check", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_unreachable_target_is_a_failed_check(capsys):
    assert target_check.main([f"tcp://127.0.0.1:{free_port()}", "--timeout", "0.5"]) == 1
    out = capsys.readouterr().out
    assert "FAIL" in out and "cannot connect to the target" in out

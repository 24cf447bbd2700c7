"""``hil target-check``: the scripted conformance session against the C reference
target (local and tcp), the Python cv target, and a target with a broken clock."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from hil.adapters.sdk import Endpoint
from hil.harness.cli import main as cli

from hil.harness.check import target_check
from tests.adapters.tcp.pair import tcp_echo
from tests.adapters.zenoh.pair import free_port
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
    assert len(rows) == 18 and set(rows.values()) == {"PASS"}, out
    assert "command 'status'" in rows and "18 of 18 checks passed" in out
    assert "one ESTIMATE per camera (CAP_CAMERAS): frame_id 2000..2002" in out  # PROTOCOL.md 4.2.1
    assert {"payload_crc without its flag", "garbage reported once"} <= set(rows)  # PROTOCOL.md 2 and 8
    assert f"clock {clock.upper()}" in out  # its own clock: the frame checks map it through clock sync


@needs_cc
@pytest.mark.parametrize("checker_token", ["the-same-token-0123456789", "another-token-0123456789", None])
def test_c_target_passes_over_tcp_and_proves_its_token(checker_token, capsys, tmp_path, monkeypatch):
    """The C target holds a token: a checker given the same one sees it proved (AUTH,
    PROTOCOL.md 4.8); given another, the connection is refused and named; given none,
    the proof is skipped and everything else passes."""
    address = f"127.0.0.1:{free_port()}"
    log = tmp_path / "c.log"
    env = dict(os.environ, **c_build.SAN_ENV, HIL_SESSION_TOKEN="the-same-token-0123456789")
    with open(log, "ab") as f:
        proc = subprocess.Popen([str(c_build.build().asan), "--transport", "tcp", "--listen", address, "--once"],
                                stdout=f, stderr=f, env=env)
    try:
        args = [f"tcp://{address}", "--timeout", "3"]
        if checker_token is not None:
            monkeypatch.setenv("CHECK_TOKEN", checker_token)
            args += ["--token-env", "CHECK_TOKEN"]
        code = target_check.main(args)
        out = capsys.readouterr().out
        rows = _rows(out)
        if checker_token == "another-token-0123456789":
            assert code == 1 and rows["auth (token proof)"] == "FAIL" and "wrong proof" in out, out
        else:
            assert code == 0, out
            assert ("proved the token in $CHECK_TOKEN" if checker_token else "give --token-env NAME") in out, out
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
    (["local", "--", "/no/such/target"], "target command not found or not executable: '/no/such/target'"),
    (["tcp://127.0.0.1:1", "--timeout", "0"], "--timeout must be > 0 s (got 0)"),
    (["tcp://127.0.0.1:1", "--vehicle", "-1"], "--vehicle must be in 0..4294967295 (got -1)"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert cli.main(["target-check", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_unreachable_target_is_a_failed_check(capsys):
    # --timeout bounds the wait for a target at an address (only one the checker
    # starts itself gets LOCAL_START_S for its HELLO): not the 5 s it once waited.
    began = time.monotonic()
    assert target_check.main([f"tcp://127.0.0.1:{free_port()}", "--timeout", "0.5"]) == 1
    assert time.monotonic() - began < target_check.LOCAL_START_S - 1.0
    out = capsys.readouterr().out
    assert "FAIL" in out and "cannot connect to the target" in out


@pytest.mark.parametrize(("cameras", "says"), [
    ("set", "one ESTIMATE per set (CAP_FRAME_SETS): the set without camera 1 answered as set 2003 once set 2006 began"),
    ("each", "one ESTIMATE per camera (CAP_CAMERAS): the set without camera 1 answered for the cameras that came"),
    ("one", "skipped: the target announces no CAP_CAMERAS"),
])
def test_sdk_rig_targets_pass_as_their_hello_declares(cameras, says, capsys, tmp_path):
    """PROTOCOL.md 4.2.1: an SDK target answering per set, per camera, or a single
    camera's target (which gets no set) passes the rig checks, in a real process."""
    address = f"127.0.0.1:{free_port()}"
    env = {k: v for k, v in os.environ.items() if k != "HIL_SESSION_TOKEN"}
    with tcp_echo(tmp_path / "t.log", ["--cameras", cameras, "--once"], listen=address, env=env):
        code = target_check.main([f"tcp://{address}", "--timeout", "3"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert says in out, out


def test_an_sdk_rig_target_passes_over_the_local_transport(capsys):
    """Over local (one message a packet) each frame of a set goes as its own message:
    three frames sent as one write were one packet with 18,640 trailing bytes."""
    code = target_check.main(["local", "--", sys.executable, "-m", "hil.targets.echo", "--cameras", "set"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "one ESTIMATE per set (CAP_FRAME_SETS): frame_id 2000" in out, out


@needs_cc
def test_c_target_answering_per_set_passes(capsys, monkeypatch):
    for k, v in c_build.SAN_ENV.items():
        monkeypatch.setenv(k, v)
    code = target_check.main(["local", "--", str(c_build.build().asan), "--frame-sets"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "one ESTIMATE per set (CAP_FRAME_SETS): frame_id 2000" in out, out


def _check_served(ep: Endpoint) -> int:
    """``hil target-check`` against the SDK endpoint ``ep`` served over TCP here; its exit code."""
    import threading

    from hil.adapters.tcp.options import TcpOptions
    from hil.adapters.tcp.target import serve_endpoint

    address = f"127.0.0.1:{free_port()}"
    t = threading.Thread(target=serve_endpoint, args=(ep,), kwargs={"options": TcpOptions(listen=address)},
                         daemon=True)
    t.start()
    try:
        return target_check.main([f"tcp://{address}", "--timeout", "2"])
    finally:
        ep.stop()
        t.join(timeout=10)


def test_a_second_answer_to_a_frame_is_named_not_blamed_on_the_next_frames(capsys):
    """A target that answers frame 1000 twice: the row of the frame during which the
    second answer came names it; the frames after it pass (each took the answer before
    as its own: "frame_id is 1000, expected 1001", then 1001 for 1002)."""
    from hil.adapters.wire.messages import Control, DrivingState, Estimate, Inference, Message

    class Twice(Endpoint):
        def send_stamped(self, make) -> None:  # type: ignore[no-untyped-def]
            super().send_stamped(make)
            m: Message = make(self.clock.now_ns())
            if isinstance(m, Estimate) and m.frame_id == 1000:
                super().send_stamped(make)

    code = _check_served(Twice(lambda f: Inference(DrivingState.SAFE, Control()), target_name="twice"))
    out = capsys.readouterr().out
    rows = _rows(out)
    assert code == 1 and rows["frame RGB8 -> estimate"] == "PASS", out
    assert rows["frame BGR8 -> estimate"] == "FAIL" and rows["frame JPEG -> estimate"] == "PASS", out
    line = next(ln for ln in out.splitlines() if ln.startswith("frame BGR8"))
    assert "a second ESTIMATE for frame 1000, answered before" in line and "expected" not in line, line


def test_a_target_whose_answers_break_its_hello_fails_in_one_line(capsys):
    """A target that declares CAP_FRAME_SETS but answers every camera fails the rig
    rows, each in one line naming the frame_ids and offset 16."""
    from hil.adapters.wire import protocol
    from hil.adapters.wire.messages import Control, DrivingState, Hello, Inference

    class Liar(Endpoint):
        def hello(self) -> Hello:
            h = super().hello()
            return Hello(h.target_name, h.protocol_version, h.clock_id, h.clock_resolution_ns,
                         h.capabilities | protocol.CAP_FRAME_SETS)

    code = _check_served(Liar(lambda f: Inference(DrivingState.SAFE, Control()), target_name="liar", cameras="each"))
    out = capsys.readouterr().out
    rows = _rows(out)
    assert code == 1 and rows["frame set of 3 cameras"] == "FAIL" and rows["frame set missing a camera"] == "FAIL", out
    line = next(ln for ln in out.splitlines() if ln.startswith("frame set of 3 cameras"))
    assert "an ESTIMATE with frame_id 2001 (offset 16), expected [2000]" in line, line

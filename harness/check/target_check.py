"""``hil target-check ENDPOINT``: a scripted session against any target, checked
against PROTOCOL.md, for device makers before their first real run.

ENDPOINT is one of::

    tcp://HOST:PORT            the target listens; the checker connects (section 10.5)
    tcp-listen://HOST:PORT     the checker listens; the target dials in
    zenoh://tcp/HOST:PORT      a Zenoh target (section 10.2; --vehicle, --key-prefix)
    can://INTERFACE/CHANNEL    a CAN FD target (section 10.3), e.g. can://socketcan/vcan0
    local -- COMMAND ARGS...   a program started as a local target (section 10.1)

The session: HELLO (over TCP with ``--token-env NAME``: and the AUTH proof of the
token in that environment variable, PROTOCOL.md 4.8); a clock-sync burst; one FRAME
of each encoding (RGB8, BGR8, JPEG); a HEARTBEAT; malformed messages (bad header CRC,
bad version, bad payload CRC, ``payload_crc`` without its flag, bytes without a
magic, the same garbage split over two writes); a COMMAND if the target announces
``CAP_COMMANDS``; frame sets if it announces ``CAP_CAMERAS`` (``target_rig``); BYE. Each check prints one row: PASS or FAIL, the PROTOCOL.md section, and what was
wrong with the byte offsets of the fields concerned. Exit 0 when all pass, 1 when
any fails, 2 for a bad endpoint or option.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from typing import Any

import numpy as np

from hil.adapters.can.options import CanOptions
from hil.adapters.link import Link, Received, open_link
from hil.adapters.local.options import LocalOptions
from hil.adapters.tcp.handshake import parse_address
from hil.adapters.tcp.options import TcpOptions
from hil.adapters.transports import TransportOptions
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Bye, Command, ErrorMsg, Estimate, Heartbeat, Hello, ImageEncoding
from hil.adapters.zenoh.options import ZenohOptions
from hil.common.errors import HilError, ProtocolError, TransportError
from hil.harness.check.target_faults import CAM, _still_alive, check_malformed
from hil.harness.check.target_rig import check_cameras
from hil.harness.check.target_session import Check, Session
from hil.timing.clock import MonotonicClock

EXIT_PASS, EXIT_FAIL, EXIT_USAGE = 0, 1, 2
W, H = 320, 240
KNOWN_CAPS = 0x0000_001F  # SHM_FRAMES | CAP_COMMANDS | CAP_AUTH | CAP_CAMERAS | CAP_FRAME_SETS


def parse_endpoint(endpoint: str, command: list[str], *, vehicle_id: int,
                   key_prefix: str) -> tuple[str, TransportOptions, dict[str, Any]]:
    """ENDPOINT (and the command after ``--`` for ``local``) -> (transport, its options
    model, what else its link takes: a local link's ``command``).

    Raises:
        TransportError: not one of the forms in the module docstring.
    """
    if endpoint == "local":
        if not command:
            raise TransportError("local: give the target's command after --, e.g. hil target-check local -- ./t")
        if shutil.which(command[0]) is None:  # a typo, not a target that fails the checks
            raise TransportError(f"local: target command not found or not executable: {command[0]!r}")
        return "local", LocalOptions(), {"command": command}
    scheme, sep, rest = endpoint.partition("://")
    if not sep:
        raise TransportError(f"ENDPOINT {endpoint!r}: expected tcp://HOST:PORT, tcp-listen://HOST:PORT, "
                             "zenoh://tcp/HOST:PORT, can://INTERFACE/CHANNEL or local -- COMMAND")
    if scheme == "tcp":
        parse_address(rest, field="ENDPOINT")
        return "tcp", TcpOptions(connect=rest), {}
    if scheme == "tcp-listen":
        parse_address(rest, field="ENDPOINT")
        return "tcp", TcpOptions(listen=rest), {}
    if scheme == "zenoh":
        return "zenoh", ZenohOptions(connect=(rest,), key_prefix=key_prefix), {}
    if scheme == "can":
        interface, _, channel = rest.partition("/")
        if not interface or not channel:
            raise TransportError(f"ENDPOINT {endpoint!r}: expected can://INTERFACE/CHANNEL, e.g. can://socketcan/vcan0")
        return "can", CanOptions(interface=interface, channel=channel), {}
    raise TransportError(f"ENDPOINT {endpoint!r}: unknown scheme {scheme!r} (tcp, tcp-listen, zenoh, can, local)")


def _image(encoding: ImageEncoding) -> bytes | None:
    """A 320x240 test picture: a gradient with a dark centre; None without OpenCV (JPEG)."""
    y, x = np.mgrid[0:H, 0:W]
    bgr = np.stack([(x * 255 // W), (y * 255 // H), np.full_like(x, 128)], axis=-1).astype(np.uint8)
    bgr[H // 3:2 * H // 3, W // 3:2 * W // 3] = 20
    if encoding == ImageEncoding.BGR8:
        return bgr.tobytes()
    if encoding == ImageEncoding.RGB8:
        return bgr[:, :, ::-1].tobytes()
    try:
        import cv2
    except ImportError:
        return None
    ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return jpg.tobytes() if ok else None


def check_hello(s: Session, hello: Hello) -> None:
    p = []
    if not hello.target_name:
        p.append("name is empty (name_len, offset 66)")
    if hello.clock_resolution_ns <= 0:
        p.append("clock_resolution_ns is 0 (offset 68)")
    if hello.capabilities & ~KNOWN_CAPS:
        p.append(f"capabilities 0x{hello.capabilities:08x} set bits v1 does not define (offset 72)")
    s.add("hello", "4.1", p, f"{hello.target_name!r}, clock {hello.clock_id.name}, resolution "
          f"{hello.clock_resolution_ns} ns, capabilities 0x{hello.capabilities:x}")


def check_auth(s: Session, hello: Hello, token_env: str | None) -> None:
    """The AUTH proof (PROTOCOL.md 4.8): over TCP the link has checked it already
    (a wrong or missing proof refuses the connection: the hello row fails)."""
    announced = bool(hello.capabilities & protocol.CAP_AUTH)
    if s.link.transport_name != "tcp":
        why = "a local target is the harness's own child" if s.link.transport_name == "local" else "tcp only"
        s.add("auth (token proof)", "4.8", [], f"skipped: the AUTH proof is checked over tcp ({why})")
    elif token_env:
        s.add("auth (token proof)", "4.8", [], f"proved the token in ${token_env} (HMAC-SHA256 of a fresh challenge)")
    else:
        s.add("auth (token proof)", "4.8", [], "skipped: the target announces CAP_AUTH; give --token-env NAME to "
              "check its proof" if announced else "skipped: the target announces no CAP_AUTH (a harness that "
              "requires a token refuses it)")


def check_sync(s: Session, n: int = 16) -> tuple[int, int] | None:
    """A burst of ``n`` exchanges; returns (target clock offset, round trip) of the
    tightest one, ns, or None when any check failed."""
    best: tuple[int, int] | None = None
    p: list[str] = []
    answered = 0
    for _ in range(n):
        before = s.link.clock.now_ns()
        m = s.link.sync_exchange(timeout_s=s.timeout_s)
        if m is None:
            p.append(f"no SYNC_RESPONSE to seq {s.link._sync_seq} within {s.timeout_s:g} s")  # noqa: SLF001
            break
        answered += 1
        if not before <= m.t1_ns <= m.t4_ns:
            p.append(f"seq {m.seq}: t1 (offset 24) is not the echo of the request's ({m.t1_ns})")
        if m.t2_target_ns > m.t3_target_ns:
            p.append(f"seq {m.seq}: t2 (offset 32) is after t3 (offset 40) by {m.t2_target_ns - m.t3_target_ns} ns")
        rtt = (m.t4_ns - m.t1_ns) - (m.t3_target_ns - m.t2_target_ns)
        offset = ((m.t2_target_ns - m.t1_ns) + (m.t3_target_ns - m.t4_ns)) // 2
        if best is None or rtt < best[1]:
            best = (offset, rtt)
    good = (f"{answered} of {n} answered; tightest round trip {best[1] / 1e3:.0f} µs, "
            f"target clock offset {best[0] / 1e6:+.3f} ms") if best else ""
    s.add("clock sync burst", "3, 4.4", p[:3], good)
    return best if not p else None


def _stray(got: int, fid: int, sent: list[int], answered: set[int]) -> str:
    """What an ESTIMATE for frame ``got`` is while the answer to ``fid`` is awaited."""
    if got in answered:
        return f"a second ESTIMATE for frame {got}, answered before (one per frame, PROTOCOL.md 4.3)"
    if got in sent:
        return f"the ESTIMATE for frame {got} came after frame {fid} was sent (answers out of order)"
    return f"an ESTIMATE for frame {got}, which was never sent (frame_id, offset 16)"


def check_frames(s: Session, sync: tuple[int, int] | None) -> None:
    sent: list[int] = []
    answered: set[int] = set()
    for k, enc in enumerate((ImageEncoding.RGB8, ImageEncoding.BGR8, ImageEncoding.JPEG)):
        data = _image(enc)
        name = f"frame {enc.name} -> estimate"
        if data is None:
            s.add(name, "4.2, 4.3", [], "skipped: JPEG needs OpenCV on the checker's side")
            continue
        fid = 1000 + k
        t_tx = s.link.send_frame(frame_id=fid, sim_time_ns=fid * 50_000_000, t0_ns=s.link.clock.now_ns(),
                                 width=W, height=H, encoding=enc, camera=CAM, ego_speed_mps=5.0, data=data)
        sent.append(fid)
        p: list[str] = []  # this frame's problems: ESTIMATEs for other frames that came meanwhile first

        def answer(r: Received, fid: int = fid, p: list[str] = p) -> bool:  # (this frame's)
            if isinstance(r.msg, Estimate) and r.msg.frame_id != fid:
                p.append(_stray(r.msg.frame_id, fid, sent, answered))
                answered.add(r.msg.frame_id)
                return False
            return isinstance(r.msg, (Estimate, ErrorMsg))

        r = s.wait_for(answer)
        if r is None or not isinstance(r.msg, Estimate):
            why = f"ERROR {r.msg.code}: {r.msg.message}" if r is not None and isinstance(r.msg, ErrorMsg) \
                else f"no ESTIMATE for frame {fid} within {s.timeout_s:g} s"
            s.add(name, "4.2, 4.3", [*p, why], "")
            continue
        e = r.msg
        assert isinstance(e, Estimate)  # what wait_for was asked for
        answered.add(fid)
        if e.vehicle_id != s.link.vehicle_id:
            p.append(f"vehicle_id (offset 8) is {e.vehicle_id}, expected {s.link.vehicle_id}")
        t_rx, t_reply = e.t_rx_target_ns, e.t_reply_target_ns
        got = [("t_rx", 24, t_rx), ("t_infer_start", 32, e.t_infer_start_target_ns),
               ("t_infer_end", 40, e.t_infer_end_target_ns), ("t_reply", 48, t_reply)]
        stamps = [(a, o, v) for a, o, v in got if v is not None]  # the wire always carries all four
        if t_rx is None or t_reply is None or len(stamps) < len(got):
            s.add(name, "3, 4.3", ["an ESTIMATE without its four target stamps"], "")
            continue
        for (a, oa, va), (b, ob, vb) in zip(stamps, stamps[1:]):
            if va > vb:
                p.append(f"{a} (offset {oa}) is after {b} (offset {ob}) by {va - vb} ns")
        if sync is not None and not p:
            offset, rtt = sync
            slack = rtt + 1_000_000  # the sync's own uncertainty plus 1 ms
            rx, reply = t_rx - offset, t_reply - offset
            if rx < t_tx - slack:
                p.append(f"t_rx (offset 24) maps to {(t_tx - rx) / 1e6:.3f} ms before the frame was sent")
            if reply > r.t_rx_ns + slack:
                p.append(f"t_reply (offset 48) maps to {(reply - r.t_rx_ns) / 1e6:.3f} ms after the estimate arrived")
        s.add(name, "3, 4.2, 4.3", p, f"{e.state.name}, steer {e.control.steering_rad:+.3f} rad, throttle "
              f"{e.control.throttle:.2f}, brake {e.control.brake:.2f}, {len(e.objects)} objects; target "
              f"{(t_reply - t_rx) / 1e6:.2f} ms")


def check_heartbeat(s: Session) -> None:
    s.drain()
    s.link.send_raw(protocol.encode(Heartbeat(s.link.vehicle_id, s.link.clock.now_ns())))
    err = s.wait_for(lambda r: isinstance(r.msg, ErrorMsg), timeout_s=0.3)
    p = ([f"the target answered a HEARTBEAT with ERROR {err.msg.code}: {err.msg.message!r}"]
         if err is not None and isinstance(err.msg, ErrorMsg) else [])
    if (gone := _still_alive(s)) is not None:
        p.append(gone)
    s.add("heartbeat accepted", "4.4", p, "no reply, session goes on")


def check_command(s: Session) -> None:
    hello = s.link.hello
    if hello is None or not hello.capabilities & protocol.CAP_COMMANDS:
        s.add("command", "4.7", [], "skipped: the target does not announce CAP_COMMANDS")
        return
    cmd = s.link.send_command("status")
    r = s.wait_for(lambda r: isinstance(r.msg, Command))
    p: list[str] = []
    if r is None:
        p.append(f"no COMMAND reply within {s.timeout_s:g} s")
    else:
        m = r.msg
        assert isinstance(m, Command)  # what wait_for was asked for
        if m.seq != cmd.seq:
            p.append(f"reply sequence (offset 16) is {m.seq}, expected {cmd.seq}")
        if m.vehicle_id != s.link.vehicle_id:
            p.append(f"reply vehicle_id (offset 8) is {m.vehicle_id}, expected {s.link.vehicle_id}")
        if not (m.text.startswith("ok") or m.text.startswith("error:")):
            p.append(f"reply text (offset 66) starts with neither 'ok' nor 'error:': {m.text[:40]!r}")
    s.add("command 'status'", "4.7", p, f"reply {r.msg.text[:60]!r}" if r is not None and isinstance(r.msg, Command)
          else "")


def check_bye(s: Session) -> None:
    s.drain()
    s.link.send_raw(protocol.encode(Bye(s.link.vehicle_id, "target-check done")))
    deadline = time.monotonic() + max(3.0, s.timeout_s)
    while s.link.alive and time.monotonic() < deadline:
        s.link.recv(timeout_s=0.05)
    p = [] if not s.link.alive else [f"still connected {max(3.0, s.timeout_s):g} s after BYE"]
    s.add("bye ends the session", "1", p, s.link.peer_gone_reason or "closed")


LOCAL_START_S = 5.0  # a target the checker starts itself gets this long for its HELLO at least


def run_checks(link: Link, *, timeout_s: float, token_env: str | None = None, hello_timeout_s: float | None = None,
               ) -> list[Check]:
    """The scripted session on a built (not opened) link; always closes it.
    ``hello_timeout_s``: how long the HELLO may take (default ``timeout_s``; a
    process the checker starts takes its start-up on top)."""
    s = Session(link, timeout_s)
    dispatch = link._dispatch  # noqa: SLF001 - record what the target sent that did not decode

    def recording(item: object, t_rx_ns: int, uncertainty_ns: int = 0) -> None:
        if isinstance(item, ProtocolError):
            s.decode_errors.append(str(item))
        dispatch(item, t_rx_ns, uncertainty_ns)  # type: ignore[arg-type]

    link._dispatch = recording  # type: ignore[method-assign]  # noqa: SLF001
    try:
        try:
            hello = link.open(hello_timeout_s=timeout_s if hello_timeout_s is None else hello_timeout_s)
        except HilError as err:
            # The link refuses a target whose proof fails during its handshake: that
            # is the AUTH row's failure (its reason names the AUTH challenge or CAP_AUTH).
            proof = token_env is not None and "AUTH" in str(err)
            s.add("auth (token proof)" if proof else "hello", "4.8" if proof else "1, 4.1", [str(err)], "")
            return s.rows
        check_hello(s, hello)
        check_auth(s, hello, token_env)
        sync = check_sync(s)
        check_frames(s, sync)
        check_cameras(s)
        check_heartbeat(s)
        check_malformed(s)
        check_command(s)
        check_bye(s)
    except (TransportError, OSError) as err:
        s.add("session", "10", [f"transport failed: {err}"], "")
    finally:
        link.close()
    s.add("everything the target sent decodes", "2-5", s.decode_errors[:5],
          f"{link.stats.messages_received} messages")
    return s.rows


def format_table(rows: list[Check]) -> str:
    width = max(len(r.name) for r in rows)
    lines = [f"{'check':<{width}}  {'PROTOCOL.md':<12}  result  detail"]
    lines += [f"{r.name:<{width}}  §{r.section:<11}  {'PASS' if r.ok else 'FAIL':<6}  {r.detail}" for r in rows]
    failed = sum(not r.ok for r in rows)
    lines.append(f"{len(rows) - failed} of {len(rows)} checks passed" + (f", {failed} FAILED" if failed else ""))
    return "\n".join(lines) + "\n"


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("target-check", help="check a target against PROTOCOL.md with a scripted session",
                       description=__doc__.split("\n\n")[0], epilog="ENDPOINT: tcp://HOST:PORT, "
                       "tcp-listen://HOST:PORT, zenoh://tcp/HOST:PORT, can://INTERFACE/CHANNEL, local -- COMMAND")
    p.add_argument("endpoint", help="how to reach the target (see below)")
    p.add_argument("target_command", nargs="*", metavar="-- COMMAND",
                   help="local: the target's command and its options, after --")
    p.add_argument("--vehicle", type=int, default=0, help="vehicle id the target serves (default 0)")
    p.add_argument("--key-prefix", default=ZenohOptions.key_prefix,
                   help=f"zenoh key prefix (default {ZenohOptions.key_prefix})")
    p.add_argument("--timeout", type=float, default=5.0,
                   help=f"seconds to wait for each answer, the HELLO included (default 5; a target started with "
                        f"local -- COMMAND gets at least {LOCAL_START_S:g} s for its HELLO)")
    p.add_argument("--token-env", default=None, metavar="NAME",
                   help="tcp: check the target's AUTH proof of the token in this environment variable "
                        "(PROTOCOL.md 4.8)")
    from hil.harness.report.ci_outputs import add_ci_args

    add_ci_args(p)


def cmd(args: argparse.Namespace) -> int:
    command = list(args.target_command)
    if command[:1] == ["--"]:
        command = command[1:]
    if command and args.endpoint != "local":
        print(f"hil target-check: error: unexpected arguments {' '.join(command)!r} (only local takes a command)",
              file=sys.stderr)
        return EXIT_USAGE
    bad = (f"--timeout must be > 0 s (got {args.timeout:g})" if not args.timeout > 0 else
           f"--vehicle must be in 0..4294967295 (got {args.vehicle})" if not 0 <= args.vehicle <= 0xFFFF_FFFF else None)
    if bad:
        print(f"hil target-check: error: {bad}", file=sys.stderr)
        return EXIT_USAGE
    from hil.harness.report.ci_outputs import CiCase, CiReport, check_ci_args, write_ci_outputs

    try:
        check_ci_args(args)
        transport, options, extra = parse_endpoint(args.endpoint, command, vehicle_id=args.vehicle,
                                                   key_prefix=args.key_prefix)
        if args.token_env:
            if not isinstance(options, TcpOptions):
                raise TransportError("--token-env: the AUTH proof is checked over tcp only")
            options = options.for_run(started=False, token_env=args.token_env, field="--token-env")
        link = open_link(transport, vehicle_id=args.vehicle, clock=MonotonicClock(), options=options, **extra)
    except HilError as err:
        print(f"hil target-check: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    # A target started here imports and starts before it can say HELLO; one at an
    # address is already running, and --timeout is what the user gave it.
    hello_s = max(args.timeout, LOCAL_START_S) if transport == "local" else args.timeout
    rows = run_checks(link, timeout_s=args.timeout, token_env=args.token_env, hello_timeout_s=hello_s)
    sys.stdout.write(format_table(rows))
    code = EXIT_PASS if all(r.ok for r in rows) else EXIT_FAIL
    cases = [CiCase(r.name, r.ok, r.detail, {"section": f"PROTOCOL.md §{r.section}"}, group="protocol") for r in rows]
    try:
        write_ci_outputs(CiReport("target-check", args.endpoint, cases, code, {"endpoint": args.endpoint}), args)
    except HilError as err:
        print(f"hil target-check: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    return code


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hil")
    add_parser(p.add_subparsers(dest="command", required=True))
    return cmd(p.parse_args(["target-check", *(sys.argv[1:] if argv is None else argv)]))


__all__ = ["Check", "add_parser", "cmd", "format_table", "main", "parse_endpoint", "run_checks"]


if __name__ == "__main__":
    raise SystemExit(main())

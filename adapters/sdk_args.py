"""The command line every target program shares: ``--transport`` and each
transport's options (``add_transport_args``, ``transport_options``), a parser whose
user mistakes are one line (``TargetArgumentParser``), and ``run_target``, which
turns an unusable transport (a port in use, ``HIL_LOCAL_FD`` unset) into one line
and exit 2. Re-exported by ``hil.adapters.sdk``."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from typing import Any, NoReturn

from hil.adapters import transports
from hil.common.errors import ConfigError

TRANSPORTS = transports.NAMES  # the transport names, from the table in hil.adapters.transports


def add_transport_args(parser: argparse.ArgumentParser) -> None:
    """Add the transport options every target program shares: ``--transport`` and the
    options of each transport (ignored by the others)."""
    g = parser.add_argument_group("transport")
    g.add_argument("--transport", choices=TRANSPORTS, default="local",
                   help="local: started by `hil run`; zenoh: network; can: CAN bus; "
                        "mixed: frames over zenoh, everything else on the CAN bus; "
                        "tcp: one TCP connection (listen, or connect to the harness)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="zenoh: endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable); "
                        "tcp: host:port to listen on for the harness (default 127.0.0.1:7600)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="zenoh: endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable); "
                        "tcp: host:port of a listening harness")
    g.add_argument("--mode", choices=("peer", "client"), default="peer", help="zenoh session mode")
    g.add_argument("--key-prefix", default=os.environ.get("HIL_ZENOH_KEY_PREFIX", "hil"),
                   help="zenoh: key expression prefix (default: $HIL_ZENOH_KEY_PREFIX, which a harness that "
                        "starts this target sets to its run's own keys, else 'hil')")
    g.add_argument("--vehicle", type=int, default=0, help="vehicle id this target serves (zenoh, can, mixed)")
    g.add_argument("--interface", default="socketcan",
                   help="can: python-can interface (socketcan, pcan, kvaser, vector, slcan, virtual)")
    g.add_argument("--channel", default="vcan0", help="can: channel, e.g. vcan0, PCAN_USBBUS1")
    g.add_argument("--bitrate", type=int, default=500_000, help="can: nominal bitrate (bit/s)")
    g.add_argument("--data-bitrate", type=int, default=2_000_000, help="can: CAN FD data bitrate (bit/s)")
    g.add_argument("--tls", action="append", default=[], metavar="KEY=VALUE",
                   help="zenoh: a transport/link/tls option, e.g. listen_certificate=dev.pem, "
                        "listen_private_key=dev.key, enable_mtls=true, root_ca_certificate=ca.pem (repeatable)")
    g.add_argument("--auth-dictionary", default=None, metavar="FILE",
                   help="zenoh: admit only peers whose user:password is a line of FILE (Zenoh usrpwd)")
    g.add_argument("--token-env", default="HIL_SESSION_TOKEN", metavar="NAME",
                   help="tcp: the environment variable holding the token this target proves to the harness "
                        "(PROTOCOL.md 4.8; default HIL_SESSION_TOKEN, which a harness that starts the target sets)")
    g.add_argument("--keep-serving", dest="keep_serving", action="store_true", default=None,
                   help="zenoh, tcp, can, mixed: serve harness after harness until Ctrl-C/SIGTERM (the default of "
                        "`hil target`)")
    g.add_argument("--once", dest="keep_serving", action="store_false",
                   help="serve one harness, then exit (the default of `python -m hil.targets.NAME`)")


def _zenoh_security(args: argparse.Namespace) -> dict[str, object]:
    """``tls`` and ``usrpwd`` options from ``--tls KEY=VALUE`` and ``--auth-dictionary`` (else
    the run's own credentials in ``HIL_ZENOH_AUTH``, set by a harness that starts the target)."""
    out: dict[str, object] = {}
    tls: dict[str, object] = {}
    for item in getattr(args, "tls", None) or []:
        from hil.adapters.zenoh.options import tls_key_problem

        key, sep, value = item.partition("=")
        problem = "KEY=VALUE, e.g. listen_certificate=dev.pem" if not sep or not key else tls_key_problem(key)
        if problem is not None:
            print(f"--tls {item!r}: expected {problem}", file=sys.stderr)
            raise SystemExit(2)  # a user mistake: one line, exit 2
        tls[key] = {"true": True, "false": False}.get(value.lower(), value)
    if tls:
        out["tls"] = tls
    if getattr(args, "auth_dictionary", None):
        out["usrpwd"] = {"dictionary_file": args.auth_dictionary}
    else:  # started by a harness: the run's own credentials, from the environment
        from hil.adapters.zenoh.options import usrpwd_from_env

        try:
            creds = usrpwd_from_env()
        except ConfigError as err:
            print(str(err), file=sys.stderr)
            raise SystemExit(2) from None
        if creds is not None:
            out["usrpwd"] = creds
    return out


def transport_options(args: argparse.Namespace) -> dict[str, Any]:
    """The keyword options ``serve`` passes to ``args.transport``."""
    if args.transport == "zenoh":
        return {"listen": list(args.listen), "connect": list(args.connect), "mode": args.mode,
                "key_prefix": args.key_prefix, "vehicle_id": args.vehicle,
                "keep_serving": bool(getattr(args, "keep_serving", False)),
                **_zenoh_security(args)}
    if args.transport == "can":
        return {"interface": args.interface, "channel": args.channel, "bitrate": args.bitrate,
                "data_bitrate": args.data_bitrate, "vehicle_id": args.vehicle,
                "keep_serving": bool(getattr(args, "keep_serving", False))}
    if args.transport == "mixed":  # the zenoh options for frames, the can options for the rest
        return {"listen": list(args.listen), "connect": list(args.connect), "mode": args.mode,
                "key_prefix": args.key_prefix, "interface": args.interface, "channel": args.channel,
                "bitrate": args.bitrate, "data_bitrate": args.data_bitrate, "vehicle_id": args.vehicle,
                "keep_serving": bool(getattr(args, "keep_serving", False)), **_zenoh_security(args)}
    if args.transport == "tcp":  # the last --listen / --connect given
        return {"listen": args.listen[-1] if args.listen else None,
                "connect": args.connect[-1] if args.connect else None,
                "keep_serving": bool(getattr(args, "keep_serving", False)), "token_env": args.token_env}
    if args.transport == "ros2":  # the node's domain, topics and Cyclone set-up come from the environment
        return {"vehicle_id": args.vehicle, "keep_serving": bool(getattr(args, "keep_serving", False))}
    return {}


class TargetArgumentParser(argparse.ArgumentParser):
    """A target program's parser: a user mistake is one line (naming the option and
    where help is) and exit 2, not argparse's usage block."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def run_target(prog: str, serve_it: Callable[[], object]) -> int:
    """Run a target program's serving: what stops it before or while serving that is
    not a bug (an unusable transport, a port in use, a bad option, ``HIL_LOCAL_FD``
    unset) is one line on stderr and exit 2; Ctrl-C ends it quietly (exit 0)."""
    from hil.common.errors import HilError

    try:
        serve_it()
    except HilError as err:
        print(f"{prog}: {err}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt:
        return 0
    return 0


__all__ = ["TRANSPORTS", "TargetArgumentParser", "add_transport_args", "run_target", "transport_options"]

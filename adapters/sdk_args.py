"""The command line every target program shares: ``--transport`` and each
transport's options (``add_transport_args``; their defaults are the transports'
options models'), the options model ``serve`` hands the transport
(``transport_options``), a parser whose user mistakes are one line
(``TargetArgumentParser``), and ``run_target``, which turns an unusable transport (a
port in use, ``HIL_LOCAL_FD`` unset) into one line and exit 2. Re-exported by
``hil.adapters.sdk``."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from typing import Any, NoReturn

from hil.adapters import transports
from hil.adapters.can.options import CanOptions
from hil.adapters.mixed.options import MixedOptions
from hil.adapters.tcp.options import DEFAULT_ADDRESS, TcpOptions
from hil.adapters.zenoh.options import PREFIX_ENV, ZenohOptions, parse_tls, target_usrpwd
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
                        f"tcp: host:port to listen on for the harness (default {DEFAULT_ADDRESS})")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="zenoh: endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable); "
                        "tcp: host:port of a listening harness")
    g.add_argument("--mode", choices=("peer", "client"), default=ZenohOptions.mode, help="zenoh session mode")
    g.add_argument("--key-prefix", default=os.environ.get(PREFIX_ENV, ZenohOptions.key_prefix),
                   help=f"zenoh: key expression prefix (default: ${PREFIX_ENV}, which a harness that "
                        f"starts this target sets to its run's own keys, else {ZenohOptions.key_prefix!r})")
    g.add_argument("--vehicle", type=int, default=0, help="vehicle id this target serves (zenoh, can, mixed)")
    g.add_argument("--interface", default=CanOptions.interface,
                   help="can: python-can interface (socketcan, pcan, kvaser, vector, slcan, virtual)")
    g.add_argument("--channel", default=CanOptions.channel, help="can: channel, e.g. vcan0, PCAN_USBBUS1")
    g.add_argument("--bitrate", type=int, default=CanOptions.bitrate, help="can: nominal bitrate (bit/s)")
    g.add_argument("--data-bitrate", type=int, default=CanOptions.data_bitrate,
                   help="can: CAN FD data bitrate (bit/s)")
    g.add_argument("--tls", action="append", default=[], metavar="KEY=VALUE",
                   help="zenoh: a transport/link/tls option, e.g. listen_certificate=dev.pem, "
                        "listen_private_key=dev.key, enable_mtls=true, root_ca_certificate=ca.pem (repeatable)")
    g.add_argument("--auth-dictionary", default=None, metavar="FILE",
                   help="zenoh: admit only peers whose user:password is a line of FILE (Zenoh usrpwd)")
    g.add_argument("--token-env", default=TcpOptions.token_env, metavar="NAME",
                   help="tcp: the environment variable holding the token this target proves to the harness "
                        f"(PROTOCOL.md 4.8; default {TcpOptions.token_env}, which a harness that starts the target "
                        "sets)")
    g.add_argument("--keep-serving", dest="keep_serving", action="store_true", default=None,
                   help="zenoh, tcp, can, mixed: serve harness after harness until Ctrl-C/SIGTERM (the default of "
                        "`hil target`)")
    g.add_argument("--once", dest="keep_serving", action="store_false",
                   help="serve one harness, then exit (the default of `python -m hil.targets.NAME`)")


def _zenoh(args: argparse.Namespace) -> ZenohOptions:
    """``--listen``/``--connect``/``--mode``/``--key-prefix``, ``--tls KEY=VALUE`` and
    ``--auth-dictionary`` (else the run's own credentials in ``HIL_ZENOH_AUTH``, set by
    a harness that starts the target)."""
    return ZenohOptions(listen=tuple(args.listen), connect=tuple(args.connect), mode=args.mode,
                        key_prefix=args.key_prefix, tls=parse_tls(getattr(args, "tls", None) or []),
                        usrpwd=target_usrpwd(getattr(args, "auth_dictionary", None)))


def _can(args: argparse.Namespace) -> CanOptions:
    return CanOptions(interface=args.interface, channel=args.channel, bitrate=args.bitrate,
                      data_bitrate=args.data_bitrate)


def _mixed(args: argparse.Namespace) -> MixedOptions:
    return MixedOptions(zenoh=_zenoh(args), can=_can(args))


def _tcp(args: argparse.Namespace) -> TcpOptions:  # the last --listen / --connect given
    return TcpOptions(listen=args.listen[-1] if args.listen else None,
                      connect=args.connect[-1] if args.connect else None, token_env=args.token_env)


def transport_options(args: argparse.Namespace) -> dict[str, Any]:
    """The keyword options ``serve`` passes to ``args.transport``'s ``serve_endpoint``:
    its options model (``options``: ``ZenohOptions``, ``CanOptions``, ``MixedOptions``
    or ``TcpOptions``), ``vehicle_id`` and ``keep_serving``; none for ``local`` (the
    harness hands it everything); a ROS 2 node takes the rest from its environment.
    A bad option is a user mistake: one line on stderr and exit 2."""
    kind = transports.transport_of(args.transport)
    keep = {"keep_serving": bool(getattr(args, "keep_serving", False))}
    try:
        if kind is transports.Transport.LOCAL:
            return {}
        if kind is transports.Transport.TCP:
            return {"options": _tcp(args), **keep}
        if kind is transports.Transport.ROS2:
            return {"vehicle_id": args.vehicle, **keep}
        options = {transports.Transport.ZENOH: _zenoh, transports.Transport.CAN: _can,
                   transports.Transport.MIXED: _mixed}[kind](args)
    except ConfigError as err:
        print(str(err), file=sys.stderr)
        raise SystemExit(2) from None
    return {"options": options, "vehicle_id": args.vehicle, **keep}


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

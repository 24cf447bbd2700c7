"""Adapters: the wire, the transports (each a harness half and a device half) and the
target SDK.

Layout::

    wire/          what a message is and its bytes: messages, protocol (the codec of
                   PROTOCOL.md), stream (bytes -> messages), receipt (stamps on a
                   stream socket), auth (a run's token, proved)
    local/ tcp/ zenoh/ can/ mixed/ ros2/
                   one package per transport, each with
                     link.py     the harness half: a Link
                     target.py   the device half: serve_endpoint(ep, ...)
                     options.py  its options model (LocalOptions, TcpOptions,
                                 ZenohOptions, CanOptions, MixedOptions, Ros2Options):
                                 the one home of its defaults, read by both halves,
                                 the harness's config and the SDK's command line;
                                 a run's own secrets (for_run) and what a target the
                                 harness starts is told (child_env)
                   and its private pieces (local: shm, shared_link/shared_target;
                   tcp: handshake; zenoh: session, shared_target; can: bus, peer,
                   dbc + hil.dbc, capacity; ros2: answers, dds, msgs + msg/, cdr)
    link.py        the harness half's base: Link (stamping, queues, drops) and
                   open_link(transport, options=...)
    transports.py  the table: transport name -> its link, serve function, options model
    sdk.py         the target SDK (Endpoint, serve); sdk_args.py its command line
    batching.py    a shared target's batching; impair.py link faults; process.py
                   child processes

A device half never imports a harness half (``link``), and nothing here imports the
harness: the SDK runs on a device with numpy and its transport's library only.
Imports numpy and ``timing`` only at package level; each transport imports its
library (zenoh, python-can, cyclonedds) inside its own modules.
"""

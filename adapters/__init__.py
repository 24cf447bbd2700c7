"""Adapters: the wire protocol codec, the transports (harness-side links and
target-side endpoints) and the target SDK.

Imports numpy and ``timing`` only at package level; each transport imports its
library (zenoh, python-can) inside its own module.
"""

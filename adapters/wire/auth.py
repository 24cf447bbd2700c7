"""Proof that a peer is the run's own target: a shared token, never sent.

PROTOCOL.md section 4.8. The harness and the target share a token: a per-run secret
the harness puts in the environment of a target it starts (``HIL_SESSION_TOKEN``),
or one the user gives both sides for a target started by hand (an environment
variable on each side, never a file). The harness sends a fresh 32-byte challenge
in an AUTH message; the target answers with ``HMAC-SHA256(token, "HIL-AUTH-1" ||
challenge || vehicle_id as u32 little-endian)``. The token itself never travels, so
a peer that listens in or answers first learns nothing it could reuse, and a
challenge is never repeated, so an answer cannot be replayed.

Standard library only (``hmac``, ``hashlib``, ``secrets``).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets

from hil.adapters.wire.protocol import AUTH_DATA_SIZE
from hil.common.errors import ConfigError

ENV_TOKEN = "HIL_SESSION_TOKEN"  # where a target finds the token (the harness sets it for a target it starts)
CONTEXT = b"HIL-AUTH-1"
MIN_TOKEN_BYTES = 16


def new_token() -> str:
    """A per-run token: 32 random bytes as 64 hex digits."""
    return secrets.token_hex(32)


def new_challenge() -> bytes:
    """32 random bytes, never repeated."""
    return secrets.token_bytes(AUTH_DATA_SIZE)


def proof(token: bytes, challenge: bytes, vehicle_id: int) -> bytes:
    """The answer to ``challenge`` for ``vehicle_id``: 32 bytes."""
    return hmac.new(token, CONTEXT + bytes(challenge) + int(vehicle_id).to_bytes(4, "little"), hashlib.sha256).digest()


def verify(token: bytes, challenge: bytes, vehicle_id: int, answer: bytes) -> bool:
    """Whether ``answer`` proves ``token`` (compared in constant time)."""
    return hmac.compare_digest(proof(token, challenge, vehicle_id), bytes(answer))


def token_from_env(name: str, *, field: str, required: bool) -> bytes | None:
    """The token in environment variable ``name`` as bytes (UTF-8), or None when it is
    unset and not ``required``.

    Raises:
        ConfigError: ``required`` and unset, or shorter than ``MIN_TOKEN_BYTES``
            (the message names ``field`` and the variable, never the value).
    """
    value = os.environ.get(name, "")
    if not value:
        if required:
            raise ConfigError(f"{field}: the environment variable {name} is not set (the shared token is never "
                              f"stored in a config; e.g. export {name}=$(openssl rand -hex 32) on both sides)")
        return None
    raw = value.encode("utf-8")
    if len(raw) < MIN_TOKEN_BYTES:
        raise ConfigError(f"{field}: the token in {name} is {len(raw)} bytes; use at least {MIN_TOKEN_BYTES} "
                          f"(e.g. openssl rand -hex 32)")
    return raw


__all__ = ["CONTEXT", "ENV_TOKEN", "MIN_TOKEN_BYTES", "new_challenge", "new_token", "proof", "token_from_env",
           "verify"]

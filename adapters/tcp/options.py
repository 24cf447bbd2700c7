"""Options of the tcp transport (standard library only): the addresses either side
listens on or dials, receipt stamps and heartbeats, and the token that proves a
target is the run's own (PROTOCOL.md 4.8)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from hil.adapters.wire.auth import ENV_TOKEN, new_token, token_from_env

DEFAULT_PORT = 7600
DEFAULT_ADDRESS = f"127.0.0.1:{DEFAULT_PORT}"  # loopback: nothing is reachable from elsewhere unless asked


@dataclass(frozen=True)
class TcpOptions:
    """The tcp transport's options, for both halves; each uses the fields that concern
    it. Addresses are ``host:port`` (a ``tcp/`` prefix is accepted); give ``connect``
    or ``listen``, not both; neither: ``DEFAULT_ADDRESS`` (the harness dials it, a
    target listens on it).

    Attributes:
        connect: the address to dial (the harness: a target that listens; a target: a
            harness that listens).
        listen: the address to listen on for the other side to dial in.
        kernel_stamps: the harness stamps receipt with the kernel's receive time
            (``SO_TIMESTAMPNS``) rather than when its reader woke.
        heartbeat_idle_s: the harness sends a HEARTBEAT after this long (s) without
            sending (0: never).
        token: the secret the target must prove (the harness's side), or None to accept
            a target that proves none (a version-1 target started by hand).
        expect_name: the harness accepts only a HELLO whose name starts with this.
        token_env: the environment variable a target reads the token it proves from.
        connect_timeout_s: how long a dialling target retries (s) before it gives up.
    """

    connect: str | None = None
    listen: str | None = None
    kernel_stamps: bool = True
    heartbeat_idle_s: float = 0.25
    token: str | None = field(default=None, repr=False)  # a secret: never in a repr
    expect_name: str | None = None
    token_env: str = ENV_TOKEN
    connect_timeout_s: float = 30.0

    def for_run(self, *, started: bool, token_env: str | None = None, field: str = "token_env") -> TcpOptions:
        """These options with the token of a run: the one in the environment variable
        ``token_env`` (set on both sides by hand), else, for a target the harness
        starts itself (``started``), a fresh secret of this run, else none.

        Raises:
            ConfigError: ``token_env`` is unset or holds under 16 bytes (the message
                names ``field``, never the value).
        """
        if token_env:
            raw = token_from_env(token_env, field=field, required=True)
            assert raw is not None
            return replace(self, token=raw.decode("utf-8"))
        return replace(self, token=new_token() if started else None)

    def child_env(self) -> dict[str, str]:
        """What a target the harness starts is told: the token it proves, in
        ``ENV_TOKEN`` (never written to the run folder)."""
        return {ENV_TOKEN: self.token} if self.token else {}


__all__ = ["DEFAULT_ADDRESS", "DEFAULT_PORT", "TcpOptions"]

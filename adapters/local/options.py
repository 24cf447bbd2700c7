"""Options of the local transport (no imports beyond the standard library's and the
frame ring's constants): how a child target finds its socket, and the shared-memory
frame ring the harness offers it."""

from __future__ import annotations

ENV_FD = "HIL_LOCAL_FD"  # the descriptor of the child's end of the socket pair

__all__ = ["ENV_FD"]

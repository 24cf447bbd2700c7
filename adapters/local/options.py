"""Options of the local transport: the shared-memory frame ring the harness offers a
child target, and how the child finds its socket. Standard library only (and the
ring's constants)."""

from __future__ import annotations

from dataclasses import dataclass

from hil.adapters.local.shm import DEFAULT_INLINE_BELOW, DEFAULT_SLOT_BYTES, DEFAULT_SLOTS

ENV_FD = "HIL_LOCAL_FD"  # the descriptor of the child's end of the socket pair


@dataclass(frozen=True)
class LocalOptions:
    """The local link's frame ring (``hil.adapters.local.shm``); the child target takes
    no options (it finds its socket and ring in ``HIL_LOCAL_FD``/``HIL_LOCAL_SHM``).

    Attributes:
        shm: offer the ring (used only if the target advertises ``SHM_FRAMES`` in its HELLO).
        shm_slots: slots in the ring (1..64); a slot is reused ``shm_slots`` frames later.
        shm_slot_bytes: largest FRAME message (64 + 40 + image bytes) a slot holds;
            larger frames go inline (counted in ``LocalLink.local_stats.too_big_for_slot``).
        shm_inline_below: FRAME messages shorter than this (bytes) stay inline.
    """

    shm: bool = True
    shm_slots: int = DEFAULT_SLOTS
    shm_slot_bytes: int = DEFAULT_SLOT_BYTES
    shm_inline_below: int = DEFAULT_INLINE_BELOW

    def child_env(self) -> dict[str, str]:
        """Nothing: the link itself hands the child its socket and ring."""
        return {}


__all__ = ["ENV_FD", "LocalOptions"]

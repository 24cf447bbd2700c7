"""The session of ``hil target-check`` (``hil.harness.check.target_check``): the link
under test, what the target sent that did not decode, and the result rows."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from hil.adapters.link import Link, Received


@dataclass
class Check:
    name: str
    section: str
    ok: bool
    detail: str


@dataclass
class Session:
    """The link under test, what it could not decode, and the rows so far."""

    link: Link
    timeout_s: float
    decode_errors: list[str] = field(default_factory=list)
    rows: list[Check] = field(default_factory=list)
    _seen: list[Received] = field(default_factory=list, init=False, repr=False)  # waited past, kept for drain()

    def add(self, name: str, section: str, problems: list[str], good: str) -> bool:
        self.rows.append(Check(name, section, not problems, "; ".join(problems) if problems else good))
        return not problems

    def wait_for(self, want: Callable[[Received], bool], timeout_s: float | None = None) -> Received | None:
        """The first received message ``want`` accepts; the rest are kept for ``drain``."""
        deadline = time.monotonic() + (timeout_s if timeout_s is not None else self.timeout_s)
        while (left := deadline - time.monotonic()) > 0:
            r = self.link.recv(timeout_s=min(left, 0.05))
            if r is None:
                if not self.link.alive:
                    return None
                continue
            if want(r):
                return r
            self._seen.append(r)
        return None

    def drain(self) -> list[Received]:
        out, self._seen = self._seen, []
        return out


__all__ = ["Check", "Session"]

"""``--shard i/N``: a deterministic slice of a campaign.

Slice ``i`` of ``N`` holds the episodes whose index ``% N == i``: slices are disjoint,
cover the campaign, and each is spread over the whole campaign (and over every
generation of a guided one), so slices take about the same time.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from hil.common.errors import ConfigError

_SHARD_RE = re.compile(r"^\s*(-?\d+)\s*/\s*(-?\d+)\s*$")


@dataclass(frozen=True)
class Shard:
    """Slice ``index`` of ``count``: the episodes ``i`` with ``i % count == index``."""

    index: int = 0
    count: int = 1

    def owns(self, episode: int) -> bool:
        return episode % self.count == self.index

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def parse_shard(text: str) -> Shard:
    """``"i/N"`` (0 <= i < N) as a Shard.

    Raises:
        ConfigError: not ``i/N``, ``N < 1``, or ``i`` outside ``0..N-1``.
    """
    m = _SHARD_RE.match(text or "")
    if not m:
        raise ConfigError(f"--shard {text!r}: expected i/N (this is slice i of N, 0 <= i < N), e.g. 0/4")
    i, n = int(m[1]), int(m[2])
    if n < 1:
        raise ConfigError(f"--shard {text}: N = {n}; expected at least 1 slice (e.g. 0/1 for the whole campaign)")
    if not (0 <= i < n):
        raise ConfigError(f"--shard {text}: index {i} out of range; expected 0 <= i < {n} "
                          f"(slices of {n} are numbered 0 to {n - 1})")
    return Shard(i, n)


__all__ = ["Shard", "parse_shard"]

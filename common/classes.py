"""What an object is, one list for the whole project: the wire's class codes
(PROTOCOL.md, ``ObjectClass`` in an ESTIMATE's objects), the world's entities and
their ground truth (``label``: ``"vehicle"`` ...), and the CNN's heatmap channels
(``DETECTABLE``, in channel order)."""

from __future__ import annotations

from enum import IntEnum


class ObjectClass(IntEnum):
    UNKNOWN = 0
    VEHICLE = 1
    PEDESTRIAN = 2
    OBSTACLE = 3

    @property
    def label(self) -> str:
        """The name ground truth, reports and recordings use: ``"pedestrian"``."""
        return self.name.lower()

    @classmethod
    def of(cls, code: int) -> ObjectClass:
        """The class of a wire code; codes this version does not know are UNKNOWN."""
        try:
            return cls(code)
        except ValueError:
            return cls.UNKNOWN


# The classes an AI is asked to detect (the CNN's heatmap channels, in this order).
DETECTABLE = (ObjectClass.VEHICLE, ObjectClass.PEDESTRIAN, ObjectClass.OBSTACLE)

__all__ = ["DETECTABLE", "ObjectClass"]

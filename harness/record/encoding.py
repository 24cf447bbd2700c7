"""How the recording's messages become bytes: compact JSON by orjson.

Chosen by measurement (``bench/bench_recorder.py``, "What a message costs"): on the
run's messages orjson is 7-13x faster than the standard library's encoder (a pipeline
record 0.9 against 5.9 µs, a ground truth of 18 entities 4.2 against 56 µs) and gives
the same JSON: compact, keys in order, NaN and infinities as ``null`` (JSON has
neither; Foxglove's parser rejects the ``NaN`` literal), numpy scalars and arrays as
numbers and lists. Only the spelling of some floats differs (``0.00001`` for
``1e-05``), which every JSON reader reads as the same number, so recordings made
before and after read alike.

Images stay JSON too (``foxglove.CompressedImage``/``RawImage`` with base64 data):
binary (protobuf) images would save ~10 µs per 12 KB JPEG frame, but every reader of
the JSON channels (the report's thumbnails, the run folder, the live view) would need
a second path; measured and left (bench/README.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson

_OPTIONS = orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS


def _default(value: Any) -> Any:
    """What orjson does not take itself: numpy arrays it cannot serialise directly
    (not contiguous, or of an odd dtype) and numpy scalars of other kinds."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


def dumps(obj: Any) -> bytes:
    """``obj`` as compact JSON bytes (NaN and infinities as ``null``).

    Raises:
        TypeError: something in ``obj`` has no JSON form (orjson's ``JSONEncodeError``
            is a ``TypeError``), or an integer beyond 64 bits.
    """
    return orjson.dumps(obj, default=_default, option=_OPTIONS)


__all__ = ["dumps"]

"""Small helpers shared by the tests (array backends, float32 rounding)."""

from __future__ import annotations

import math
import struct
from typing import Any, List


def flat(a: Any) -> List[float]:
    """The components of a numpy array or an array.array as a flat list of Python numbers."""
    if hasattr(a, "reshape"):
        return a.reshape(-1).tolist()
    return list(a)


def f32(x: float) -> float:
    """``x`` rounded to float32, as the server's JSON printed it."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def norm_floats(v: Any) -> Any:
    """A JSON-like value with every float rounded to float32, so that the server's shortest
    float32 spelling (``1.5259022e-5``) and the decoded value compare equal."""
    if isinstance(v, float):
        return f32(v)
    if isinstance(v, dict):
        return {k: norm_floats(x) for k, x in v.items()}
    if isinstance(v, list):
        return [norm_floats(x) for x in v]
    return v


def diagonal(bbox: Any) -> float:
    """The length of a box's diagonal (the scale tolerances are relative to)."""
    return math.dist(bbox.min, bbox.max)

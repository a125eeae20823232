"""Vertex payloads (``f32``, ``f16``, ``q16``) and index payloads turned into arrays.

With numpy (``backend="numpy"``) positions and normals are ``float32`` arrays of shape
``(vertices, 3)`` and indices ``uint32`` arrays of shape ``(triangles, 3)``; ``f32`` payloads
are zero-copy, read-only views of the response body (the server aligns them to 16 bytes for
that), so ``.copy()`` one to write into it. Without numpy (``backend="python"``) they are flat
:class:`array.array` objects (``'f'`` and ``'I'``), x, y, z per vertex.

Dequantization follows ``proto/README.md``: q16 positions are
``min[a] + (q + 32768) × step[a]`` per axis ``a`` and q16 normals ``q / 32767``. The numpy path
computes in float32 in the order the Rust reference does, so its values are the reference's
bit for bit; the pure-Python path computes in double and rounds once to float32.
"""

from __future__ import annotations

import struct
import sys
from array import array
from typing import Any, Optional, Sequence

try:  # numpy is optional: the package is standard library only.
    import numpy as _np
except ImportError:  # pragma: no cover - exercised on machines without numpy
    _np = None

__all__ = [
    "HAVE_NUMPY",
    "resolve_backend",
    "component_bytes",
    "decode_positions",
    "decode_normals",
    "decode_f32",
    "decode_u32",
    "q16r_decode",
]

#: Whether numpy could be imported.
HAVE_NUMPY = _np is not None

_LITTLE = sys.byteorder == "little"


def _index_typecode() -> str:
    """The array typecode of a 4-byte unsigned integer on this platform."""
    for code in ("I", "L"):
        if array(code).itemsize == 4:
            return code
    raise RuntimeError("no 4-byte unsigned array typecode on this platform")


_U32_CODE = _index_typecode()


def resolve_backend(backend: str) -> str:
    """``"auto"`` (numpy when installed), ``"numpy"`` or ``"python"``."""
    if backend == "auto":
        return "numpy" if HAVE_NUMPY else "python"
    if backend == "numpy":
        if not HAVE_NUMPY:
            raise ImportError("arrays='numpy' needs numpy installed (pip install numpy)")
        return backend
    if backend == "python":
        return backend
    raise ValueError(f"arrays must be 'auto', 'numpy' or 'python', not {backend!r}")


def component_bytes(fmt: str) -> int:
    """Bytes of one component in a vertex format."""
    if fmt == "f32":
        return 4
    if fmt in ("f16", "q16"):
        return 2
    raise ValueError(f"unknown vertex format {fmt!r} (f32, f16 or q16)")


def _check_len(
    data: Any, vertices: Optional[int], width: int, what: str, components: int = 3
) -> None:
    n = len(data)
    per = components * width
    if n % per:
        raise ValueError(f"{what}: {n} bytes is not a whole number of {per}-byte vertices")
    if vertices is not None and n != vertices * per:
        raise ValueError(
            f"{what}: {n} bytes, expected {vertices} vertices × {components} × {width}"
        )


def _flat(typecode: str, data: Any) -> array:
    a = array(typecode)
    a.frombytes(data)
    if not _LITTLE:  # pragma: no cover - big-endian machines
        a.byteswap()
    return a


def decode_f32(
    data: Any, backend: str, vertices: Optional[int] = None, components: int = 3
) -> Any:
    """Little-endian float32, ``components`` per vertex (x, y, z; or u, v with 2)."""
    _check_len(data, vertices, 4, "f32 payload", components)
    if backend == "numpy":
        return _np.frombuffer(data, dtype="<f4").reshape(-1, components)
    return _flat("f", data)


def decode_u32(data: Any, backend: str) -> Any:
    """Little-endian uint32 triangle indices."""
    if len(data) % 12:
        raise ValueError(f"index payload: {len(data)} bytes is not whole triangles of 3 × u32")
    if backend == "numpy":
        return _np.frombuffer(data, dtype="<u4").reshape(-1, 3)
    return _flat(_U32_CODE, data)


def _decode_f16(data: Any, backend: str) -> Any:
    if backend == "numpy":
        return _np.frombuffer(data, dtype="<f2").astype(_np.float32).reshape(-1, 3)
    n = len(data) // 2
    # struct's 'e' is IEEE binary16; every binary16 value is exact in float32.
    return array("f", struct.unpack(f"<{n}e", data))


def decode_positions(
    data: Any,
    fmt: str,
    quantization: Any,
    backend: str,
    vertices: Optional[int] = None,
) -> Any:
    """Positions in rig space from a payload of format ``fmt`` (``quantization`` for q16)."""
    width = component_bytes(fmt)
    _check_len(data, vertices, width, f"{fmt} positions")
    if fmt == "f32":
        return decode_f32(data, backend)
    if fmt == "f16":
        return _decode_f16(data, backend)
    if quantization is None:
        raise ValueError("q16 positions need the buffer's quantization box")
    lo: Sequence[float] = quantization.min
    step: Sequence[float] = quantization.step
    if backend == "numpy":
        f32 = _np.float32
        # The reference's float32 operations in its order, min + (q + 32768) * step, done in
        # place: one array allocated instead of three for a 30 MB crowd.
        out = _np.frombuffer(data, dtype="<i2").astype(f32).reshape(-1, 3)
        out += f32(32768.0)
        out *= _np.asarray(step, dtype=f32)
        out += _np.asarray(lo, dtype=f32)
        return out
    q = _flat("h", data)
    lx, ly, lz = lo
    sx, sy, sz = step
    out = array("f", bytes(4 * len(q)))
    out[0::3] = array("f", [lx + (v + 32768) * sx for v in q[0::3]])
    out[1::3] = array("f", [ly + (v + 32768) * sy for v in q[1::3]])
    out[2::3] = array("f", [lz + (v + 32768) * sz for v in q[2::3]])
    return out


def decode_normals(data: Any, fmt: str, backend: str, vertices: Optional[int] = None) -> Any:
    """Unit normals from a payload of format ``fmt`` (q16 normals are ``q / 32767``)."""
    width = component_bytes(fmt)
    _check_len(data, vertices, width, f"{fmt} normals")
    if fmt == "f32":
        return decode_f32(data, backend)
    if fmt == "f16":
        return _decode_f16(data, backend)
    if backend == "numpy":
        out = _np.frombuffer(data, dtype="<i2").astype(_np.float32).reshape(-1, 3)
        out /= _np.float32(32767.0)
        return out
    return array("f", [v / 32767.0 for v in _flat("h", data)])


def q16r_decode(planes: Any, reference: Any) -> bytes:
    """The q16 bytes (int16 little-endian) that ``q16r`` residual ``planes`` code against the
    q16 bytes ``reference`` (``proto/README.md``, "Vertex data"): for ``n`` values, ``planes``
    are the ``n`` low bytes then the ``n`` high bytes of ``z = zigzag(q - r)`` (the wrapping
    int16 difference), so ``q = r + unzigzag(lo | hi << 8)``, wrapping. A length that does not
    match (``2 × n`` bytes of planes for ``n`` reference values) is a :class:`ValueError`.

    Session streams' temporal residuals (``TickDelta``) use the same coding, with a head's
    previous buffer as the reference."""
    if len(reference) % 2:
        raise ValueError(f"a q16 reference of {len(reference)} bytes (not whole int16 values)")
    n = len(reference) // 2
    if len(planes) != 2 * n:
        raise ValueError(f"{len(planes)} residual bytes for {n} values")
    if _np is not None:
        p = _np.frombuffer(planes, _np.uint8)
        z = p[:n].astype(_np.uint16) | (p[n:].astype(_np.uint16) << 8)
        d = (z >> 1).astype(_np.int16) ^ -(z & 1).astype(_np.int16)
        # int16 + int16 wraps in numpy, as the Rust wrapping_add does.
        return (_np.frombuffer(reference, "<i2") + d).astype("<i2").tobytes()
    r = _flat("h", reference)
    lo = bytes(planes[:n])
    hi = bytes(planes[n:])
    out = array("h", bytes(2 * n))
    for i in range(n):
        z = lo[i] | (hi[i] << 8)
        d = (z >> 1) ^ -(z & 1)
        out[i] = ((r[i] + d + 32768) & 0xFFFF) - 32768
    if not _LITTLE:  # pragma: no cover - big-endian machines
        out.byteswap()
    return out.tobytes()

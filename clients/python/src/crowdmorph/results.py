"""Decoded results: the arrays a program works with, made from the wire messages.

:class:`Buffer` (one blended buffer of a crowd frame or a session tick), :class:`CrowdFrame`
(a ``POST /v1/crowd/frame`` answer), :class:`Mesh` (``GET /v1/rigs/{id}/mesh``) and
:class:`Image` (a rendered picture, from ``POST /v1/crowd/render`` or a session stream). Their
payloads are decoded by :mod:`crowdmorph.arrays`; the raw :mod:`crowdmorph.messages` object
stays reachable (``wire`` or ``response``). :mod:`crowdmorph.client` and
:mod:`crowdmorph.sessions` both make them, so they live here, below both.
"""

from __future__ import annotations

from typing import Any, Dict, List, Sequence

from . import arrays as _arrays
from .messages import (
    Aabb,
    CrowdFrameResponse,
    FrameBuffer,
    FrameTimings,
    HeadBuffer,
    MeshPrimitive,
    MeshResponse,
    Quantization,
)

__all__ = ["Buffer", "CrowdFrame", "Mesh", "Image"]

class Buffer:
    """One unique blended buffer of a crowd frame, decoded.

    ``positions`` and ``normals`` (``None`` unless asked for) are float32 arrays: numpy
    ``(vertices, 3)`` arrays, or flat ``array('f')`` without numpy. ``quantization`` is the box
    q16 positions were decoded with (``None`` for other formats). ``wire`` is the undecoded
    :class:`~crowdmorph.messages.FrameBuffer` (its ``positions`` are the payload bytes).
    """

    __slots__ = (
        "rig",
        "clip",
        "frame",
        "lod",
        "vertices",
        "quantization",
        "positions",
        "normals",
        "wire",
    )

    def __init__(self, fb: FrameBuffer, fmt: str, backend: str):
        self.rig = fb.rig
        self.clip = fb.clip
        self.frame = fb.frame
        self.lod = fb.lod
        self.vertices = fb.vertices
        self.quantization = fb.quantization
        self.wire = fb
        self.positions = _arrays.decode_positions(
            fb.positions, fmt, fb.quantization, backend, fb.vertices
        )
        self.normals = (
            None
            if fb.normals is None
            else _arrays.decode_normals(fb.normals, fmt, backend, fb.vertices)
        )

    def __repr__(self) -> str:
        return (
            f"Buffer(rig={self.rig!r}, clip={self.clip!r}, frame={self.frame}, lod={self.lod}, "
            f"vertices={self.vertices})"
        )


class CrowdFrame:
    """A decoded crowd frame: the unique ``buffers``, and per request head (in request order)
    its :class:`~crowdmorph.messages.HeadBuffer` in ``heads`` (a
    :class:`~crowdmorph.messages.HeadBuffers`; ``heads.buffer_indices`` is an array).
    ``positions(i)`` is the positions of request head ``i``; clones share one array.
    ``response`` is the raw message."""

    __slots__ = ("format", "normals", "buffers", "heads", "timings", "response")

    def __init__(self, response: CrowdFrameResponse, backend: str):
        self.response = response
        self.format: str = response.format
        self.normals: bool = response.normals
        self.timings: FrameTimings = response.timings
        self.heads: Sequence[HeadBuffer] = response.heads
        self.buffers: List[Buffer] = [Buffer(b, response.format, backend) for b in response.buffers]
        indices = getattr(self.heads, "buffer_indices", None)
        if indices is None:
            indices = [h.buffer for h in self.heads]
        if len(indices) and max(indices) >= len(self.buffers):
            raise ValueError(f"a head names buffer {max(indices)} of {len(self.buffers)}")

    def __len__(self) -> int:
        return len(self.heads)

    def buffer(self, i: int) -> Buffer:
        """The buffer request head ``i`` uses."""
        return self.buffers[self.heads[i].buffer]

    def positions(self, i: int) -> Any:
        """Positions of request head ``i``."""
        return self.buffer(i).positions

    def __repr__(self) -> str:
        return (
            f"CrowdFrame(format={self.format!r}, heads={len(self.heads)}, "
            f"buffers={len(self.buffers)}, timings={self.timings})"
        )


class Mesh:
    """A rig's topology and neutral pose at a LOD level (``GET /v1/rigs/{id}/mesh``).

    ``indices`` (a triangle list over the concatenated vertex space), ``positions`` and
    ``normals`` are arrays as in :class:`Buffer` (numpy ``(n, 3)`` or flat ``array``);
    ``primitives`` give each primitive's vertex and index ranges; ``quantization`` is the box
    of the rig's q16 buffers. ``response`` is the raw message.
    """

    __slots__ = (
        "rig",
        "lod",
        "vertices",
        "primitives",
        "bbox",
        "quantization",
        "indices",
        "positions",
        "normals",
        "uvs",
        "uvs1",
        "colors",
        "response",
    )

    def __init__(self, response: MeshResponse, backend: str):
        self.response = response
        self.rig: str = response.rig
        self.lod: int = response.lod
        self.vertices: int = response.vertices
        self.primitives: List[MeshPrimitive] = response.primitives
        self.bbox: Aabb = response.bbox
        self.quantization: Quantization = response.quantization
        self.indices = _arrays.decode_u32(response.indices, backend)
        self.positions = _arrays.decode_f32(response.positions, backend, response.vertices)
        self.normals = _arrays.decode_f32(response.normals, backend, response.vertices)
        # Texture coordinates of set 0, (vertices, 2), or None when the rig has none.
        self.uvs = (
            _arrays.decode_f32(response.uvs, backend, response.vertices, components=2)
            if len(response.uvs)
            else None
        )
        # Texture coordinates of set 1, (vertices, 2), or None.
        self.uvs1 = (
            _arrays.decode_f32(response.uvs1, backend, response.vertices, components=2)
            if len(response.uvs1)
            else None
        )
        # Vertex colours (COLOR_0, linear RGBA), (vertices, 4), or None.
        self.colors = (
            _arrays.decode_f32(response.colors, backend, response.vertices, components=4)
            if len(response.colors)
            else None
        )

    @property
    def triangles(self) -> int:
        return len(self.response.indices) // 12

    def __repr__(self) -> str:
        return (
            f"Mesh(rig={self.rig!r}, lod={self.lod}, vertices={self.vertices}, "
            f"triangles={self.triangles})"
        )


class Image(bytes):
    """A rendered image: the body's bytes (PNG, JPEG or raw RGBA8), with ``content_type``,
    ``width``, ``height`` and ``server_timing`` (milliseconds by phase: ``compute``,
    ``render``, ``readback``, ``encode``)."""

    content_type: str
    width: int
    height: int
    server_timing: Dict[str, float]

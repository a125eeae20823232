"""Wavefront OBJ output of a posed head, for looking at one in any 3D viewer.

Coordinates are written with 9 significant digits, which round-trip float32 exactly."""

from __future__ import annotations

import os
from typing import IO, Any, Iterator, Optional, Tuple, Union

__all__ = ["write_obj"]


def _triples(a: Any) -> Iterator[Tuple[float, float, float]]:
    """x, y, z triples of a numpy ``(n, 3)`` array or a flat sequence."""
    shape = getattr(a, "shape", None)
    if shape is not None and len(shape) == 2:
        for row in a.tolist():
            yield row[0], row[1], row[2]
        return
    flat = a.tolist() if hasattr(a, "tolist") else list(a)
    if len(flat) % 3:
        raise ValueError(f"{len(flat)} components is not a whole number of x, y, z triples")
    for i in range(0, len(flat), 3):
        yield flat[i], flat[i + 1], flat[i + 2]


def write_obj(
    out: Union[str, "os.PathLike[str]", IO[str]],
    positions: Any,
    indices: Any,
    normals: Optional[Any] = None,
    comment: Optional[str] = None,
) -> Tuple[int, int]:
    """Writes a triangle mesh as OBJ and returns ``(vertices, triangles)``.

    ``positions`` (and ``normals``) are x, y, z per vertex, ``indices`` a triangle list of
    0-based vertex indices: numpy ``(n, 3)`` arrays or flat sequences, as
    :class:`crowdmorph.Mesh` and :class:`crowdmorph.CrowdFrame` give them.
    """
    if isinstance(out, (str, os.PathLike)):
        with open(out, "w", encoding="utf-8") as f:
            return write_obj(f, positions, indices, normals, comment)
    if comment:
        for line in comment.splitlines():
            out.write(f"# {line}\n")
    verts = 0
    for x, y, z in _triples(positions):
        out.write(f"v {x:.9g} {y:.9g} {z:.9g}\n")
        verts += 1
    if normals is not None:
        n = 0
        for x, y, z in _triples(normals):
            out.write(f"vn {x:.9g} {y:.9g} {z:.9g}\n")
            n += 1
        if n != verts:
            raise ValueError(f"{n} normals for {verts} vertices")
    tris = 0
    for a, b, c in _triples(indices):
        a, b, c = int(a) + 1, int(b) + 1, int(c) + 1
        if max(a, b, c) > verts:
            raise ValueError(f"triangle {tris} indexes vertex {max(a, b, c) - 1} of {verts}")
        if normals is not None:
            out.write(f"f {a}//{a} {b}//{b} {c}//{c}\n")
        else:
            out.write(f"f {a} {b} {c}\n")
        tris += 1
    return verts, tris

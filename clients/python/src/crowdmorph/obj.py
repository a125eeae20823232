"""Wavefront OBJ output of a posed head, for looking at one in any 3D viewer, with its
materials as an MTL file when the rig has them.

Coordinates are written with 9 significant digits, which round-trip float32 exactly. OBJ's
``vt`` has its origin at the bottom left and glTF's at the top left, so ``v`` is flipped."""

from __future__ import annotations

import os
from typing import IO, Any, Dict, Iterator, List, Optional, Sequence, Tuple, Union

__all__ = ["write_obj", "write_mtl"]


def _pairs(a: Any) -> Iterator[Tuple[float, float]]:
    """u, v pairs of a numpy ``(n, 2)`` array or a flat sequence."""
    shape = getattr(a, "shape", None)
    if shape is not None and len(shape) == 2:
        for row in a.tolist():
            yield row[0], row[1]
        return
    flat = a.tolist() if hasattr(a, "tolist") else list(a)
    for i in range(0, len(flat) - 1, 2):
        yield flat[i], flat[i + 1]


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
    uvs: Optional[Any] = None,
    groups: Optional[Sequence[Tuple[str, int, int, Optional[str]]]] = None,
    mtllib: Optional[str] = None,
) -> Tuple[int, int]:
    """Writes a triangle mesh as OBJ and returns ``(vertices, triangles)``.

    ``positions`` (and ``normals``) are x, y, z per vertex, ``uvs`` u, v per vertex (glTF's
    top-left origin), ``indices`` a triangle list of 0-based vertex indices: numpy arrays or
    flat sequences, as :class:`crowdmorph.Mesh` and :class:`crowdmorph.CrowdFrame` give them.
    ``groups`` names ranges of triangles ``(name, first_index, index_count, material)`` (a
    mesh's primitives), each drawn with its ``usemtl`` from the ``mtllib`` file.
    """
    if isinstance(out, (str, os.PathLike)):
        with open(out, "w", encoding="utf-8") as f:
            return write_obj(f, positions, indices, normals, comment, uvs, groups, mtllib)
    if comment:
        for line in comment.splitlines():
            out.write(f"# {line}\n")
    if mtllib:
        out.write(f"mtllib {mtllib}\n")
    verts = 0
    for x, y, z in _triples(positions):
        out.write(f"v {x:.9g} {y:.9g} {z:.9g}\n")
        verts += 1
    if uvs is not None:
        n = 0
        for u, v in _pairs(uvs):
            out.write(f"vt {u:.9g} {1.0 - v:.9g}\n")
            n += 1
        if n != verts:
            raise ValueError(f"{n} texture coordinates for {verts} vertices")
    if normals is not None:
        n = 0
        for x, y, z in _triples(normals):
            out.write(f"vn {x:.9g} {y:.9g} {z:.9g}\n")
            n += 1
        if n != verts:
            raise ValueError(f"{n} normals for {verts} vertices")
    # A face corner: the vertex, with its texture coordinate and normal of the same index.
    if uvs is not None and normals is not None:
        corner = "{0}/{0}/{0}".format
    elif uvs is not None:
        corner = "{0}/{0}".format
    elif normals is not None:
        corner = "{0}//{0}".format
    else:
        corner = "{0}".format
    # Where each group starts, by triangle.
    starts = {}
    for name, first, _count, material in groups or ():
        starts[first // 3] = (name, material)
    tris = 0
    for a, b, c in _triples(indices):
        if tris in starts:
            name, material = starts[tris]
            out.write(f"g {name}\n")
            if material:
                out.write(f"usemtl {material}\n")
        a, b, c = int(a) + 1, int(b) + 1, int(c) + 1
        if max(a, b, c) > verts:
            raise ValueError(f"triangle {tris} indexes vertex {max(a, b, c) - 1} of {verts}")
        out.write("f " + " ".join(corner(i) for i in (a, b, c)) + "\n")
        tris += 1
    return verts, tris


def _material_name(i: int, m: Dict[str, Any]) -> str:
    name = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in m.get("name") or "")
    return f"m{i}_{name}" if name else f"m{i}"


def write_mtl(
    out: Union[str, "os.PathLike[str]", IO[str]],
    materials: Dict[str, Any],
    image_files: Sequence[Optional[str]],
) -> List[str]:
    """Writes the materials of ``Client.materials(rig)`` as an MTL file and returns each
    material's name (what :func:`write_obj`'s ``groups`` use). ``image_files`` is the file
    each image was saved as (``None``: not saved). Base colour is ``Kd`` (linear, as glTF
    stores it) and ``map_Kd``; alpha is ``d`` and ``map_d`` when the material is not opaque;
    the normal map ``norm``; emissive ``Ke`` and ``map_Ke``; roughness ``Pr``, metallic ``Pm``
    (the PBR extension of MTL that Blender and others read)."""
    if isinstance(out, (str, os.PathLike)):
        with open(out, "w", encoding="utf-8") as f:
            return write_mtl(f, materials, image_files)
    textures = materials.get("textures", [])

    def image_of(info: Optional[Dict[str, Any]]) -> Optional[str]:
        if not info:
            return None
        t = textures[info["index"]] if info["index"] < len(textures) else {}
        src = t.get("source")
        return image_files[src] if src is not None and src < len(image_files) else None

    names = []
    for i, m in enumerate(materials.get("materials", [])):
        name = _material_name(i, m)
        names.append(name)
        pbr = m.get("pbrMetallicRoughness", {})
        r, g, b, a = pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0])
        out.write(f"newmtl {name}\n")
        out.write(f"Kd {r:.6g} {g:.6g} {b:.6g}\n")
        out.write(f"Pr {pbr.get('roughnessFactor', 1.0):.6g}\n")
        out.write(f"Pm {pbr.get('metallicFactor', 1.0):.6g}\n")
        ke = m.get("emissiveFactor", [0.0, 0.0, 0.0])
        out.write(f"Ke {ke[0]:.6g} {ke[1]:.6g} {ke[2]:.6g}\n")
        blended = m.get("alphaMode", "OPAQUE") != "OPAQUE"
        if blended:
            out.write(f"d {a:.6g}\n")
        base = image_of(pbr.get("baseColorTexture"))
        if base:
            out.write(f"map_Kd {base}\n")
            if blended:
                out.write(f"map_d {base}\n")
        normal = image_of(m.get("normalTexture"))
        if normal:
            out.write(f"norm {normal}\n")
        emissive = image_of(m.get("emissiveTexture"))
        if emissive:
            out.write(f"map_Ke {emissive}\n")
        out.write("\n")
    return names

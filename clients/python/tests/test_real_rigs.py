"""Real rigs from ``../shared/data`` uploaded through the client (skipped, with the reason,
when the folder is absent).

The ICT FaceKit head is checked against the file itself, read here with a few lines of
``json`` and ``struct`` (no code shared with the server): the mesh's neutral positions are the
GLB's POSITION accessor, and a frame of a one-target CSV clip is neutral + that target's deltas.
The Khronos samples come as ``.gltf`` with external buffers, which the client inlines.
"""

from __future__ import annotations

import json
import struct

import pytest

import crowdmorph
from _util import diagonal, flat

KHRONOS = [
    "AnimatedMorphCube",
    "AnimatedMorphSphere",
    "MorphPrimitivesTest",
    "MorphStressTest",
    "SimpleMorph",
]


def _glb(path):
    """A GLB's JSON document and the offset of its BIN chunk's data."""
    data = path.read_bytes()
    assert data[:4] == b"glTF"
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + json_len])
    return data, doc, 20 + json_len + 8  # the BIN chunk's length and type come first


def _vec3(data, doc, bin_start, accessor_index):
    """A dense float32 VEC3 accessor as a flat list, read straight from the file's bytes."""
    acc = doc["accessors"][accessor_index]
    assert acc["componentType"] == 5126 and acc["type"] == "VEC3" and "sparse" not in acc
    view = doc["bufferViews"][acc["bufferView"]]
    assert view.get("byteStride", 12) == 12
    start = bin_start + view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return list(struct.unpack_from(f"<{3 * acc['count']}f", data, start))


def test_the_ict_facekit_head_uploads_and_plays_a_csv_clip(client, shared_data, backend):
    path = shared_data / "ict-facekit" / "ict_facekit_53.glb"
    c = crowdmorph.Client(client.url, token=client.token, arrays=backend, timeout=300)
    rig = c.upload_rig(path, name="py-ict", replace=True)
    try:
        assert (rig.id, rig.builtin, rig.vertices, rig.triangles) == ("py-ict", False, 26719, 52220)
        assert len(rig.targets) == 53 and "jawOpen" in rig.targets
        with pytest.raises(crowdmorph.Conflict) as e:
            c.upload_rig(path, name="py-ict")
        assert e.value.code == "rig_exists"

        data, doc, bin_start = _glb(path)
        primitive = doc["meshes"][0]["primitives"][0]
        neutral = _vec3(data, doc, bin_start, primitive["attributes"]["POSITION"])
        mesh = c.mesh("py-ict")
        assert mesh.vertices == 26719 and mesh.triangles == 52220
        assert flat(mesh.positions) == neutral, "the mesh is the file's neutral pose"

        targets = doc["meshes"][0]["extras"]["targetNames"]
        jaw = primitive["targets"][targets.index("jawOpen")]["POSITION"]
        delta = _vec3(data, doc, bin_start, jaw)
        clip = c.upload_clip("py-ict", b"jawOpen\n0\n1\n", name="jaw")
        assert [(x.name, x.frames) for x in clip.added] == [("jaw", 2)]

        diag = diagonal(rig.bbox)
        exact = c.crowd_frame([(1, "py-ict", "jaw", 0), (2, "py-ict", "jaw", 1)], format="f32")
        rest, open_ = flat(exact.positions(0)), flat(exact.positions(1))
        assert max(abs(a - b) for a, b in zip(rest, neutral)) <= 1e-6 * diag
        want = [n + d for n, d in zip(neutral, delta)]
        assert max(abs(a - b) for a, b in zip(open_, want)) <= 1e-6 * diag
        assert max(abs(a - b) for a, b in zip(open_, rest)) > 0.01 * diag, "the jaw opens"

        q = c.crowd_frame([(2, "py-ict", "jaw", 1)], format="q16").buffer(0)
        err = q.quantization.max_error
        for k, (a, b) in enumerate(zip(flat(q.positions), open_)):
            assert abs(a - b) <= err[k % 3] + 4 * 2**-23 * diag, (k, a, b)
    finally:
        c.delete_rig("py-ict")
    with pytest.raises(crowdmorph.NotFound):
        c.rig("py-ict")


@pytest.mark.parametrize("name", KHRONOS)
def test_khronos_samples_upload_from_gltf_files_with_external_buffers(client, shared_data, name):
    path = shared_data / "khronos" / name / "glTF" / f"{name}.gltf"
    inlined = json.loads(crowdmorph.self_contained_gltf(path))
    assert all(b["uri"].startswith("data:") for b in inlined["buffers"])
    rig_id = f"py-{name.lower()}"
    rig = client.upload_rig(path, name=rig_id, replace=True)
    try:
        assert rig.vertices == sum(p.vertices for p in rig.primitives) > 0
        assert len(rig.primitives) == sum(len(m["primitives"]) for m in inlined["meshes"])
        mesh = client.mesh(rig_id)
        assert mesh.vertices == rig.vertices and mesh.triangles == rig.triangles
        assert [p.vertices for p in mesh.primitives] == [p.vertices for p in rig.primitives]
        # Every clip of the file plays; its buffers have the rig's vertices.
        heads = [(i, rig_id, clip.name, clip.frames // 2) for i, clip in enumerate(rig.clips)]
        assert len(rig.clips) == len(inlined.get("animations", []))
        if heads:
            frame = client.crowd_frame(heads, format="f16", normals=True)
            for i in range(len(heads)):
                assert frame.buffer(i).vertices == rig.vertices
                assert len(flat(frame.buffer(i).normals)) == 3 * rig.vertices
    finally:
        client.delete_rig(rig_id)


def test_a_textured_rig_saves_as_obj_with_its_materials_and_textures(
    client, shared_data, tmp_path
):
    """MorphPrimitivesTest (a JPEG base colour on two materials) through ``save_obj.py``: the
    OBJ names an MTL file whose ``map_Kd`` is the file's own JPEG, byte for byte, and carries
    one ``vt`` per vertex equal to the file's TEXCOORD_0 with ``v`` flipped."""
    import subprocess
    import sys
    from pathlib import Path

    folder = shared_data / "khronos" / "MorphPrimitivesTest" / "glTF"
    path = folder / "MorphPrimitivesTest.gltf"
    rig_id = "py-textured"
    client.upload_rig(path, name=rig_id, replace=True)
    try:
        looks = client.materials(rig_id)
        assert [m["name"] for m in looks["materials"]] == ["red", "green"]
        mesh = client.mesh(rig_id)
        assert [p.material for p in mesh.primitives] == [0, 1]
        out = tmp_path / "prims.obj"
        package = Path(crowdmorph.__file__).resolve().parent.parent
        env = {"PYTHONPATH": str(package), "PATH": "/usr/bin:/bin"}
        examples = Path(__file__).resolve().parent.parent / "examples"
        # The file has no animation: a one-frame clip of its first target at half weight.
        target = client.rig(rig_id).targets[0]
        client.upload_clip(rig_id, f"{target}\n0.5\n".encode(), name="half")
        subprocess.run(
            [sys.executable, str(examples / "save_obj.py"), "--url", client.url,
             "--rig", rig_id, "--clip", "half", "--frame", "0", "--out", str(out)],
            check=True, env=env, timeout=120,
        )
        lines = out.read_text().splitlines()
        assert "mtllib prims.mtl" in lines
        vts = [tuple(float(x) for x in l.split()[1:]) for l in lines if l.startswith("vt ")]
        assert len(vts) == mesh.vertices
        uvs = flat(mesh.uvs)
        for i, (u, v) in enumerate(vts):
            assert abs(u - uvs[2 * i]) < 1e-6 and abs(v - (1.0 - uvs[2 * i + 1])) < 1e-6
        assert sum(1 for l in lines if l.startswith("usemtl ")) == 2
        mtl = (tmp_path / "prims.mtl").read_text().splitlines()
        maps = [l.split()[1] for l in mtl if l.startswith("map_Kd ")]
        assert len(maps) == 2 and maps[0] == maps[1]
        assert (tmp_path / maps[0]).read_bytes() == (folder / "uv_texture.jpg").read_bytes()
        # Kd is each material's base colour factor.
        assert "Kd 1 0 0" in mtl and "Kd 0 1 0" in mtl
    finally:
        client.delete_rig(rig_id)

"""The client against a real ``crowdmorph serve``: the embedded rig ``default-head``.

Decoded arrays are checked against the server's own JSON encoding of the same request (an
independent path: serde_json and base64 on the server, ``json`` and ``base64`` here), and the
lossy formats against f32 within the error bounds ``proto/README.md`` states. Tolerances are
relative to the rig's bounding-box diagonal.
"""

from __future__ import annotations

import base64
import json
import math
import os
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

import crowdmorph
from crowdmorph import wire
from conftest import PACKAGE, TOKEN, run_server
from _util import diagonal, f32, flat, norm_floats

RIG = "default-head"
BUILTIN_CLIPS = {"idle", "talk", "smile", "surprise"}


def test_health_and_readiness(client):
    assert client.healthz() == {"status": "ok"}
    ready = client.readyz()
    assert ready.status == "ready"
    assert ready.backend in ("cpu", "gpu")
    assert ready.cpu_isa in ("avx512", "avx2", "portable")
    assert ready.rigs >= 1 and ready.skipped_files == []


def test_the_embedded_rig_is_listed_with_its_clips(client):
    rigs = {r.id: r for r in client.rigs()}
    head = rigs[RIG]
    assert head.builtin
    assert {c.name for c in head.clips} >= BUILTIN_CLIPS
    assert head == client.rig(RIG)
    assert head.vertices == sum(p.vertices for p in head.primitives) > 0
    assert head.triangles == sum(p.triangles for p in head.primitives) > 0
    assert len(head.lod.levels) >= 2 and head.lod.levels[0].shapes == len(head.targets)
    assert client.lod(RIG) == head.lod
    assert {c.name for c in client.clips(RIG)} >= BUILTIN_CLIPS
    talk = client.clip(RIG, "talk")
    assert talk.frames > 0 and talk.fps > 0


def _json_frame(client, heads, fmt, normals):
    """The same request as JSON, decoded from base64 by hand: the server's second encoding."""
    body = json.dumps(
        {
            "heads": [dict(head=h, rig=r, clip=c, frame=f, lod=lod) for h, r, c, f, lod in heads],
            "output": {"normals": normals, "format": fmt},
            "wrap": True,
        }
    ).encode()
    resp = client.request(
        "POST", "/v1/crowd/frame", body, "application/json", accept="application/json"
    )
    assert resp.content_type.startswith("application/json")
    return json.loads(resp.body)


HEADS = [(7, RIG, "talk", 12, 0), (8, RIG, "talk", 12, 0), (9, RIG, "smile", 40, 2)]


@pytest.mark.parametrize("fmt", ["f32", "f16", "q16"])
def test_bincode_frames_carry_the_bytes_of_the_servers_json(client, fmt):
    frame = client.crowd_frame(HEADS, format=fmt, normals=True, decode=False)
    want = _json_frame(client, HEADS, fmt, True)
    assert frame.format == want["format"] == fmt and frame.normals is True
    assert [(h.head, h.buffer) for h in frame.heads] == [
        (h["head"], h["buffer"]) for h in want["heads"]
    ]
    assert len(frame.buffers) == len(want["buffers"]) == 2  # heads 7 and 8 are clones
    for got, exp in zip(frame.buffers, want["buffers"]):
        assert (got.rig, got.clip, got.frame, got.lod, got.vertices) == (
            exp["rig"],
            exp["clip"],
            exp["frame"],
            exp["lod"],
            exp["vertices"],
        )
        assert bytes(got.positions) == base64.b64decode(exp["positions"])
        assert bytes(got.normals) == base64.b64decode(exp["normals"])
        if fmt == "q16":
            q = exp["quantization"]
            assert [struct.pack("<f", v) for v in got.quantization.min] == [
                struct.pack("<f", v) for v in q["min"]
            ]
        else:
            assert got.quantization is None and exp["quantization"] is None


def test_f16_and_q16_positions_are_within_their_stated_error_of_f32(client, backend):
    c = crowdmorph.Client(client.url, arrays=backend)
    diag = diagonal(c.rig(RIG).bbox)
    exact = c.crowd_frame(HEADS, format="f32", normals=True)
    half = c.crowd_frame(HEADS, format="f16", normals=True)
    quant = c.crowd_frame(HEADS, format="q16", normals=True)
    assert len(exact) == len(half) == len(quant) == 3
    for i in range(3):
        e, h, q = exact.buffer(i), half.buffer(i), quant.buffer(i)
        ep, hp, qp = flat(e.positions), flat(h.positions), flat(q.positions)
        assert len(ep) == len(hp) == len(qp) == 3 * e.vertices
        # f16: relative error ≤ 2^-11 per component (plus f16's subnormal step near 0).
        assert all(abs(a - b) <= 2**-11 * abs(a) + 2**-24 for a, b in zip(ep, hp))
        # q16: the stated max error per axis, plus float32 rounding of the largest coordinate.
        err = q.quantization.max_error
        slack = 4 * 2**-23 * diag
        for k, (a, b) in enumerate(zip(ep, qp)):
            assert abs(a - b) <= err[k % 3] + slack, (k, a, b, err)
        # Normals are unit vectors in every format; q16's error ≤ 1/65534 per component.
        en, qn = flat(e.normals), flat(q.normals)
        assert all(abs(a - b) <= 1 / 65534 + 2**-20 for a, b in zip(en, qn))
        for v in range(0, e.vertices, 97):
            assert abs(math.hypot(*en[3 * v : 3 * v + 3]) - 1) < 1e-3
    # Clones share one buffer, and a clip at another frame moves the head.
    assert exact.positions(0) is exact.positions(1)
    moved = max(abs(a - b) for a, b in zip(flat(exact.positions(0)), flat(exact.positions(2))))
    assert moved > 1e-3 * diag


def test_heads_may_be_objects_dicts_or_tuples(client):
    forms = [
        crowdmorph.Head(1, RIG, "talk", 5),
        {"head": 2, "rig": RIG, "clip": "talk", "frame": 5},
        (3, RIG, "talk", 5, 0),
        (4, RIG, "talk", 5),
    ]
    frame = client.crowd_frame(forms, format="f32")
    assert len(frame.buffers) == 1
    assert list(frame.heads.head_ids) == [1, 2, 3, 4]
    assert list(frame.heads.buffer_indices) == [0, 0, 0, 0]


def test_blends_and_live_weights(client):
    """A blend's clones share a buffer whatever their layer order; live weights by name, by
    ARKit spelling and dense agree; ``t = 1`` is the layer's frame."""
    info = client.rig(RIG)
    layers = [crowdmorph.BlendLayer("smile", 3, 0.25), {"clip": "surprise", "frame": 9, "t": 0.125}]
    frame = client.crowd_frame(
        [
            crowdmorph.Head(1, RIG, "talk", 40, blend=layers),
            {"head": 2, "rig": RIG, "clip": "talk", "frame": 40, "blend": list(reversed(layers))},
            crowdmorph.Head(3, RIG, "talk", 40, blend=[("smile", 3, 1.0)]),
            (4, RIG, "smile", 3),
        ]
    )
    assert list(frame.heads.buffer_indices) == [0, 0, 1, 1]
    dense = [0.6 if name == "jawOpen" else 0.0 for name in info.targets]
    live = client.live_frame(RIG, [{"jawOpen": 0.6}, {"JawOpen": 0.6}, dense])
    assert list(live.heads.buffer_indices) == [0, 0, 0]
    one = client.live_frame(RIG, {"jawOpen": 0.6})
    assert flat(one.positions(0)) == flat(live.positions(0))
    neutral = client.live_frame(RIG, {})
    assert flat(neutral.positions(0)) != flat(live.positions(0))
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.live_frame(RIG, {"jawOpen": 0.5, "noSuchShape": 1.0})
    assert e.value.code == "unknown_targets" and "noSuchShape" in e.value.message


def test_poses_are_the_weights_the_server_blends(client):
    """``crowd_poses``: per head its binary16 weights in the order ``rig_channels`` names;
    clones share a pose; sent back as live weights they blend to the clip frame's vertices."""
    info = client.rig(RIG)
    channels = client.rig_channels(RIG)
    assert channels.rig == RIG and channels.targets == info.targets and channels.nodes == []
    poses = client.crowd_poses(
        [(1, RIG, "talk", 40), (2, RIG, "talk", 40), {"head": 3, "rig": RIG, "weights": {"jawOpen": 0.6}}]
    )
    assert poses.format == "weights"
    assert list(poses.heads.buffer_indices) == [0, 0, 1]
    live = poses.poses[1].weights_f32()
    assert len(live) == len(channels.targets)
    jaw = channels.targets.index("jawOpen")
    assert abs(live[jaw] - 0.6) <= 0.6 * 2**-11 + 2**-13
    assert all(w == 0.0 for k, w in enumerate(live) if k != jaw)
    talk = poses.poses[0].weights_f32()
    again = client.live_frame(RIG, [talk])
    frame = client.crowd_frame([(1, RIG, "talk", 40)])
    diag = diagonal(info.bbox)
    worst = max(abs(a - b) for a, b in zip(flat(again.positions(0)), flat(frame.positions(0))))
    assert worst <= 1e-3 * diag, worst
    with pytest.raises(ValueError):
        client.crowd_frame([(1, RIG, "talk", 40)], format="weights")
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.crowd_poses([crowdmorph.Head(1, RIG, "talk", 40, lod=1)])
    assert e.value.code == "invalid_output" and "lod" in e.value.message


def test_a_large_crowd_round_trips(client):
    talk = client.clip(RIG, "talk")
    heads = [(i * 1000, RIG, "talk", i, 0) for i in range(5000)]
    frame = client.crowd_frame(heads, format="q16")
    assert len(frame) == 5000
    assert len(frame.buffers) == talk.frames  # one per distinct frame, the rest clones
    assert frame.heads[4999].head == 4999 * 1000
    assert frame.buffer(4999).frame == 4999 % talk.frames


def test_wrapping_and_frame_range(client):
    frames = client.clip(RIG, "talk").frames
    frame = client.crowd_frame([(1, RIG, "talk", frames + 3), (2, RIG, "talk", -1)])
    assert [frame.buffer(0).frame, frame.buffer(1).frame] == [3, frames - 1]
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.crowd_frame([(1, RIG, "talk", frames + 3)], wrap=False)
    assert e.value.code == "frame_out_of_range" and e.value.status == 400


def test_the_mesh_gives_topology_and_the_neutral_pose(client, backend):
    c = crowdmorph.Client(client.url, arrays=backend)
    info = c.rig(RIG)
    mesh = c.mesh(RIG)
    assert (mesh.rig, mesh.lod, mesh.vertices, mesh.triangles) == (
        RIG,
        0,
        info.vertices,
        info.triangles,
    )
    idx = flat(mesh.indices)
    assert len(idx) == 3 * info.triangles and max(idx) < info.vertices
    assert sum(p.indices for p in mesh.primitives) == len(idx)
    pos = flat(mesh.positions)
    lo, hi = mesh.bbox.min, mesh.bbox.max
    for k, v in enumerate(pos):
        assert lo[k % 3] <= v <= hi[k % 3]
    if backend == "numpy":
        assert mesh.positions.shape == (info.vertices, 3)
        assert mesh.indices.shape == (info.triangles, 3)


def test_every_lod_level_has_its_mesh_and_buffer_size(client):
    info = client.rig(RIG)
    for level, lv in enumerate(info.lod.levels):
        mesh = client.mesh(RIG, lod=level)
        assert mesh.lod == level and mesh.vertices == lv.vertices
        frame = client.crowd_frame([(level, RIG, "idle", 10, level)], format="f16")
        assert frame.buffer(0).lod == level and frame.buffer(0).vertices == lv.vertices
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.crowd_frame([(1, RIG, "idle", 0, len(info.lod.levels))])
    assert e.value.code == "lod_out_of_range"


def test_errors_are_typed_with_code_message_and_request_id(client, anonymous):
    with pytest.raises(crowdmorph.NotFound) as e:
        client.rig("no-such-rig")
    assert e.value.code == "unknown_rig" and "no-such-rig" in e.value.message
    assert e.value.request_id and e.value.request_id == client.last_request_id
    with pytest.raises(crowdmorph.NotFound) as e:
        client.crowd_frame([(1, RIG, "no-such-clip", 0)])
    assert e.value.code == "unknown_clip"
    with pytest.raises(crowdmorph.Forbidden) as e:
        client.delete_rig(RIG)
    assert e.value.code == "builtin_rig"
    with pytest.raises(crowdmorph.Forbidden) as e:
        client.delete_clip(RIG, "talk")
    assert e.value.code == "builtin_clip"
    with pytest.raises(crowdmorph.Unauthorized) as e:
        anonymous.upload_rig(b"glTF", name="nope")
    assert e.value.code == "token_required" and e.value.status == 401
    with pytest.raises(crowdmorph.Unauthorized) as e:
        crowdmorph.Client(client.url, token="wrong").delete_rig("nope")
    assert e.value.code == "bad_token"
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.upload_rig(b"this is not a rig", name="garbage")
    assert e.value.code == "invalid_rig"
    with pytest.raises(crowdmorph.UnsupportedMediaType):
        client.request("POST", "/v1/crowd/frame", b"{}", "text/plain")
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.request("POST", "/v1/crowd/frame", b"\x01\x07", crowdmorph.BINCODE)
    assert e.value.code == "malformed_bincode"
    with pytest.raises(crowdmorph.NotFound) as e:
        client.request("GET", "/v1/nothing-here")
    assert e.value.code == "no_route"
    # Reading is open without the token.
    assert anonymous.rig(RIG).id == RIG


def _csv(targets, rows):
    lines = [",".join(targets)] + [",".join(str(v) for v in row) for row in rows]
    return ("\n".join(lines) + "\n").encode()


def test_clips_upload_list_play_and_delete(client):
    info = client.rig(RIG)
    t = info.targets[:2]
    up = client.upload_clip(RIG, _csv(t, [[0, 0], [1, 0], [0, 1]]), name="py-csv")
    assert up.rig == RIG and [(c.name, c.frames) for c in up.added] == [("py-csv", 3)]
    assert up.ignored == []
    js = client.upload_clip(
        RIG, {"fps": 24, "targets": t, "frames": [[0, 0], [0.5, 0.5]]}, name="py-json"
    )
    assert [(c.name, c.frames, c.fps) for c in js.added] == [("py-json", 2, 24.0)]
    try:
        names = {c.name for c in client.clips(RIG)}
        assert {"py-csv", "py-json"} <= names
        assert client.clip(RIG, "py-csv").frames == 3
        # Frame 0 is neutral, frame 1 moves the first target: the buffers differ.
        f = client.crowd_frame([(1, RIG, "py-csv", 0), (2, RIG, "py-csv", 1)], format="f32")
        moved = max(abs(a - b) for a, b in zip(flat(f.positions(0)), flat(f.positions(1))))
        assert moved > 0
        with pytest.raises(crowdmorph.Conflict) as e:
            client.upload_clip(RIG, _csv(t, [[0, 0]]), name="py-csv")
        assert e.value.code == "clip_exists"
        with pytest.raises(crowdmorph.BadRequest) as e:
            client.upload_clip(RIG, _csv(["notATarget"], [[1]]), name="py-bad")
        assert e.value.code == "unknown_targets" and "notATarget" in e.value.message
        ign = client.upload_clip(
            RIG, _csv([t[0], "notATarget"], [[1, 1]]), name="py-ign", ignore_unknown=True
        )
        assert ign.ignored == ["notATarget"]
        client.delete_clip(RIG, "py-ign")
    finally:
        client.delete_clip(RIG, "py-csv")
        client.delete_clip(RIG, "py-json")
    with pytest.raises(crowdmorph.NotFound) as e:
        client.clip(RIG, "py-csv")
    assert e.value.code == "unknown_clip"


def test_set_lod_rebuilds_the_table():
    # Its own server, so that the shared one keeps the embedded rig's LOD.
    with run_server("--no-auto-lod") as s, crowdmorph.Client(s.url, token=TOKEN) as c:
        targets = c.rig(RIG).targets
        rig = c.set_lod(
            RIG,
            method="file-order",
            pinned=[targets[-1]],
            levels=[len(targets), (4, 0)],
            mesh_fractions=[0.5],
        )
        lod = c.wait_lod(RIG, timeout=120)
        assert lod.status == "ready", lod.error
        assert lod.pinned == [targets[-1]] and lod.order[0] == targets[-1]
        assert [lv.shapes for lv in lod.levels] == [len(targets), 4]
        assert lod.levels[0].mesh is None and lod.levels[1].mesh == 0
        assert lod.levels[1].vertices < lod.levels[0].vertices
        assert rig.lod.pinned == lod.pinned
        mesh = c.mesh(RIG, lod=1)
        assert mesh.vertices == lod.levels[1].vertices
        frame = c.crowd_frame([(1, RIG, "talk", 3, 1)], format="q16")
        assert frame.buffer(0).vertices == mesh.vertices
        with pytest.raises(crowdmorph.BadRequest) as e:
            c.set_lod(RIG, method="file-order", levels=[3])  # level 0 must use every shape
        assert e.value.code == "invalid_lod"


def test_an_upload_refused_before_its_body_is_read_raises_the_servers_413():
    # The server answers 413 and closes while 20 MB are still being sent: the client reads
    # that answer instead of reporting the broken pipe.
    with run_server("--no-auto-lod", "--max-upload-bytes", "100000") as s:
        c = crowdmorph.Client(s.url, token=TOKEN)
        with pytest.raises(crowdmorph.TooLarge) as e:
            c.upload_rig(b"glTF" + bytes(20_000_000), name="big")
        assert e.value.code == "body_too_large" and "100000" in e.value.message
        assert c.rig(RIG).id == RIG, "the client goes on with a new connection"


def test_the_connection_is_kept_alive_and_reopened_after_the_server_closes_it():
    with run_server("--no-auto-lod", "--idle-timeout-s", "1") as s, crowdmorph.Client(s.url) as c:
        ports = set()
        for _ in range(5):
            c.rig(RIG)
            ports.add(c._conn.sock.getsockname()[1])
        assert len(ports) == 1, "five calls, one connection"
        time.sleep(2.5)  # past the server's idle timeout: it closes the connection
        assert c.rig(RIG).id == RIG
        assert c._conn.sock.getsockname()[1] not in ports


def test_render_returns_an_image_or_says_why_not(client):
    heads = [(1, RIG, "talk", 0), (2, RIG, "smile", 30)]
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.render(heads, width=0, height=10)
    assert e.value.code == "invalid_image"
    # A framing camera goes as JSON; a position beside its frame is refused there.
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.render(heads, camera={"frame": "faces", "position": [0, 0, 5]})
    assert e.value.code == "invalid_camera" and "position" in e.value.message
    if client.readyz().renderer is None:
        with pytest.raises(crowdmorph.Unavailable) as e:
            client.render(heads)
        assert e.value.code == "render_unavailable" and e.value.retry_after is None
        pytest.skip("the server has no adapter to render with (install mesa-vulkan-drivers)")
    png = client.render(heads, width=64, height=48)
    assert isinstance(png, bytes) and png[:8] == b"\x89PNG\r\n\x1a\n"
    assert (png.content_type, png.width, png.height) == ("image/png", 64, 48)
    assert struct.unpack(">II", png[16:24]) == (64, 48)  # the IHDR's size
    assert {"compute", "render", "readback", "encode"} <= set(png.server_timing)
    jpeg = client.render(heads, image={"width": 32, "height": 32, "format": "jpeg"})
    assert jpeg[:2] == b"\xff\xd8" and jpeg.content_type == "image/jpeg"
    raw = client.render(
        heads,
        width=40,
        height=30,
        format="rgba",
        background=[10, 200, 30],
        camera={"position": [0, 0, 2000], "target": [0, 0, 0], "fov_y": 5},
    )
    assert len(raw) == 40 * 30 * 4 and raw.content_type == "application/octet-stream"
    # A far, narrow camera leaves the corners to the background colour.
    assert tuple(raw[0:4]) == (10, 200, 30, 255)
    assert tuple(raw[-4:]) == (10, 200, 30, 255)
    with pytest.raises(crowdmorph.BadRequest) as e:
        client.render(heads, placements=[{"head": 99, "position": [0, 0, 0]}])
    assert e.value.code == "invalid_placement"
    # Framing the faces: the same picture from heads in any form (the request goes as JSON),
    # nearer than the default view (more of the image is head, less is background);
    # framing the bodies is the default view.
    bg = [10, 200, 30]

    def background(img):
        return sum(1 for i in range(0, len(img), 4) if tuple(img[i : i + 4]) == (*bg, 255))

    size = {"width": 80, "height": 60, "format": "rgba", "background": bg}
    faces = client.render(heads, camera=crowdmorph.CameraSpec(frame="faces"), **size)
    assert faces.content_type == "application/octet-stream" and len(faces) == 80 * 60 * 4
    as_objects = [
        crowdmorph.Head(1, RIG, "talk", 0),
        {"head": 2, "rig": RIG, "clip": "smile", "frame": 30},
    ]
    assert bytes(client.render(as_objects, camera={"frame": "faces"}, **size)) == bytes(faces)
    default = client.render(heads, **size)
    assert bytes(client.render(heads, camera={"frame": "bodies"}, **size)) == bytes(default)
    assert background(faces) < background(default)


def test_the_save_obj_example_writes_the_posed_head(server, client, tmp_path):
    out = tmp_path / "head.obj"
    subprocess.run(
        [
            sys.executable,
            str(PACKAGE / "examples" / "save_obj.py"),
            "--url",
            server.url,
            "--clip",
            "smile",
            "--frame",
            "40",
            "--out",
            str(out),
        ],
        check=True,
        env=_env_with_package(),
        timeout=120,
    )
    verts, normals, faces = [], [], []
    for line in out.read_text().splitlines():
        kind, *rest = line.split()
        if kind == "v":
            verts.append([float(x) for x in rest])
        elif kind == "vn":
            normals.append([float(x) for x in rest])
        elif kind == "f":
            faces.append([int(x.split("/")[0]) - 1 for x in rest])
    info = client.rig(RIG)
    assert len(verts) == len(normals) == info.vertices
    assert len(faces) == info.triangles
    # The coordinates are the f32 frame's, exactly (9 digits round-trip float32).
    want = flat(client.crowd_frame([(1, RIG, "smile", 40)], format="f32").positions(0))
    assert [f32(x) for v in verts for x in v] == want
    assert faces[:3] == [list(t) for t in zip(*[iter(flat(client.mesh(RIG).indices)[:9])] * 3)]


def _env_with_package():
    """The environment with the tested package first on the path, installed or not."""
    env = dict(os.environ)
    src = str(Path(crowdmorph.__file__).resolve().parent.parent)
    env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def test_a_malformed_answer_is_a_protocol_error(client):
    # Decoding a RigInfo as a RigList fails at a byte offset instead of returning garbage.
    resp = client.request("GET", f"/v1/rigs/{RIG}")
    with pytest.raises(crowdmorph.ProtocolError):
        client._decode(crowdmorph.RigList, resp)
    with pytest.raises(wire.DecodeError):
        wire.decode(crowdmorph.RigList, resp.body)


@pytest.mark.parametrize("compression", ["gzip", "zstd"])
def test_compressed_answers_inflate_to_the_plain_bytes(server, compression):
    # zstd needs the optional zstandard package; gzip is the standard library's.
    if compression == "zstd":
        pytest.importorskip("zstandard", reason="zstandard is not installed (crowdmorph[zstd])")
    heads = [(i, RIG, "talk", 5 * i, 0) for i in range(8)]
    with crowdmorph.Client(server.url) as plain, crowdmorph.Client(
        server.url, compression=compression
    ) as packed:
        want = plain.crowd_frame(heads, format="q16", normals=True, decode=False)
        got = packed.crowd_frame(heads, format="q16", normals=True, decode=False)
        for a, b in zip(got.buffers, want.buffers):
            assert bytes(a.positions) == bytes(b.positions)
            assert bytes(a.normals) == bytes(b.normals)
        r = packed.request("GET", "/v1/rigs/" + RIG + "/mesh")
        assert r.headers.get("content-encoding") == compression
        assert r.wire_bytes < len(r.body)
        r = plain.request("GET", "/v1/rigs/" + RIG + "/mesh")
        assert r.headers.get("content-encoding") is None and r.wire_bytes == len(r.body)


def test_q16_residuals_decode_to_the_q16_values(client, backend):
    heads = [(i, RIG, clip, 9 * i, i % 3) for i, clip in enumerate(["talk", "smile", "idle"] * 3)]
    with crowdmorph.Client(client.url, arrays=backend, compression="gzip") as c:
        raw = c.crowd_frame(heads, format="q16r", normals=True, decode=False)
        assert raw.format == "q16r"
        q16 = c.crowd_frame(heads, format="q16", normals=True, decode=False)
        for a, b in zip(raw.buffers, q16.buffers):
            got = crowdmorph.client.q16r_decode(bytes(a.positions), c.q16_reference(a))
            assert got == bytes(b.positions)
            assert bytes(a.normals) == bytes(b.normals)
        # Decoded frames are the q16 frames.
        want = c.crowd_frame(heads, format="q16", normals=True)
        got = c.crowd_frame(heads, format="q16r", normals=True)
        for i in range(len(heads)):
            assert flat(got.positions(i)) == flat(want.positions(i))


def _skinned_triangle_glb():
    """A tiny skinned rig as GLB bytes, standard library only (as the Rust tests'
    ``skinned_triangle_rig``): the triangle (0,0,0), (1,0,0), (0,1,0) with one morph target
    ``a`` (lifts vertex 1 along +Z), skinned to ``Root`` at the origin and its child ``Jaw`` at
    (0, 1, 0): vertex 0 follows Root, vertex 1 Jaw, vertex 2 both by half."""
    chunks = []
    views = []
    accessors = []

    def add(data, count, kind, component, **extra):
        offset = sum(len(c) for c in chunks)
        chunks.append(data + b"\0" * (-len(data) % 4))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data)})
        accessors.append(
            dict(bufferView=len(views) - 1, componentType=component, count=count, type=kind)
        )
        accessors[-1].update(extra)
        return len(accessors) - 1

    f32s = lambda *v: struct.pack(f"<{len(v)}f", *v)  # noqa: E731
    position = add(
        f32s(0, 0, 0, 1, 0, 0, 0, 1, 0), 3, "VEC3", 5126, min=[0, 0, 0], max=[1, 1, 0]
    )
    indices = add(struct.pack("<3H", 0, 1, 2), 3, "SCALAR", 5123)
    lift = add(f32s(0, 0, 0, 0, 0, 1, 0, 0, 0), 3, "VEC3", 5126, min=[0, 0, 0], max=[0, 0, 1])
    joints = add(bytes([0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0]), 3, "VEC4", 5121)
    weights = add(f32s(1, 0, 0, 0, 1, 0, 0, 0, 0.5, 0.5, 0, 0), 3, "VEC4", 5126)
    identity = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
    jaw_bind = identity[:12] + [0, -1, 0, 1]  # column-major: the inverse of a (0, 1, 0) shift
    ibm = add(f32s(*identity, *jaw_bind), 2, "MAT4", 5126)
    blob = b"".join(chunks)
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [
            {"mesh": 0, "skin": 0},
            {"name": "Root", "children": [2]},
            {"name": "Jaw", "translation": [0, 1, 0]},
        ],
        "meshes": [
            {
                "primitives": [
                    {
                        "attributes": {
                            "POSITION": position,
                            "JOINTS_0": joints,
                            "WEIGHTS_0": weights,
                        },
                        "indices": indices,
                        "targets": [{"POSITION": lift}],
                    }
                ],
                "extras": {"targetNames": ["a"]},
            }
        ],
        "skins": [{"joints": [1, 2], "inverseBindMatrices": ibm}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}],
    }
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    return b"".join(
        [
            struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(text) + 8 + len(blob)),
            struct.pack("<I4s", len(text), b"JSON"),
            text,
            struct.pack("<I4s", len(blob), b"BIN\0"),
            blob,
        ]
    )


def _vertices(frame, i):
    """Head ``i``'s positions as a list of (x, y, z) tuples."""
    p = flat(frame.positions(i))
    return [tuple(p[k : k + 3]) for k in range(0, len(p), 3)]


def _close(got, want, tol=1e-5):
    return len(got) == len(want) and all(
        abs(a - b) <= tol for u, v in zip(got, want) for a, b in zip(u, v)
    )


def test_a_rigs_joint_map_turns_joints_by_clip_columns(client, anonymous):
    rig = "py-skinned"
    info = client.upload_rig(_skinned_triangle_glb(), name=rig, replace=True)
    try:
        assert info.skeleton is not None and info.targets == ["a"]
        rest = _vertices(client.crowd_frame([crowdmorph.Head(0, rig, weights={})]), 0)
        assert _close(rest, [(0, 0, 0), (1, 0, 0), (0, 1, 0)])

        # The defaults: no Head/head/J_Bip_C_Head and no eye joints here, so no channel.
        default = client.joint_map(rig)
        assert isinstance(default, crowdmorph.JointMapInfo)
        assert (default.rig, default.default, default.channels) == (rig, True, [])

        # The rig's own map: HeadYaw turns the jaw about +X, half a radian per unit. The axis
        # comes back normalized; dicts, objects and the spec all make the same map.
        own = client.set_joint_map(
            rig, [{"column": "HeadYaw", "node": "Jaw", "axis": [2, 0, 0], "scale": 0.5}]
        )
        want = crowdmorph.JointChannelSpec("HeadYaw", "Jaw", [1.0, 0.0, 0.0], 0.5)
        assert (own.rig, own.default, own.channels) == (rig, False, [want])
        assert client.joint_map(rig) == own
        spec = crowdmorph.JointMapSpec(
            [crowdmorph.JointChannelSpec("HeadYaw", "Jaw", [1, 0, 0], 0.5)]
        )
        assert client.set_joint_map(rig, spec) == own
        assert client.set_joint_map(rig, spec.channels) == own
        # The bincode answer decodes to what the server's JSON says.
        resp = client.request("GET", f"/v1/rigs/{rig}/joint-map", accept="application/json")
        assert norm_floats(json.loads(resp.body)) == crowdmorph.as_dict(own)
        # The spec's bincode layout is the server's too.
        resp = client.request(
            "PUT", f"/v1/rigs/{rig}/joint-map", crowdmorph.encode(spec), crowdmorph.BINCODE
        )
        assert crowdmorph.decode(crowdmorph.JointMapInfo, resp.body) == own
        # Defaults of a dict channel: +Y, one radian per unit.
        yaw = client.set_joint_map(rig, {"channels": [{"column": "HeadYaw", "node": "Jaw"}]})
        assert yaw.channels == [crowdmorph.JointChannelSpec("HeadYaw", "Jaw", [0, 1, 0], 1.0)]

        with pytest.raises(crowdmorph.BadRequest) as e:
            client.set_joint_map(rig, [crowdmorph.JointChannelSpec("HeadYaw", "Tail")])
        assert e.value.code == "unknown_joints" and "Tail" in e.value.message
        with pytest.raises(crowdmorph.BadRequest) as e:
            client.set_joint_map(rig, [{"column": "HeadYaw", "node": "Jaw", "axis": [0, 0, 0]}])
        assert e.value.code == "invalid_joint_map"
        with pytest.raises(crowdmorph.Unauthorized) as e:
            anonymous.set_joint_map(rig, spec)
        assert e.value.code == "token_required"
        with pytest.raises(crowdmorph.Unauthorized):
            anonymous.reset_joint_map(rig)
        with pytest.raises(crowdmorph.BadRequest) as e:
            client.set_joint_map(RIG, spec)  # the embedded head has no skeleton
        assert e.value.code == "invalid_joint_map"
        assert client.joint_map(rig) == yaw, "refused maps change nothing"
        assert anonymous.joint_map(rig) == yaw, "reading is open without the token"

        # A clip uploaded under the rig's own map: HeadYaw 0.5 turns the jaw 0.25 rad about +X,
        # carrying vertex 1 ((1, -1, 0) from the jaw) and leaving the others.
        client.set_joint_map(rig, spec)
        up = client.upload_clip(rig, _csv(["a", "HeadYaw"], [[0, 0], [0, 0.5]]), name="yaw")
        assert [(c.name, c.frames) for c in up.added] == [("yaw", 2)] and up.ignored == []
        frame = client.crowd_frame([(1, rig, "yaw", 0), (2, rig, "yaw", 1)], format="f32")
        assert len(frame.buffers) == 2
        c, s = math.cos(0.25), math.sin(0.25)
        assert _close(_vertices(frame, 0), rest)
        assert _close(_vertices(frame, 1), [(0, 0, 0), (1, 1 - c, -s), (0, 1, 0)])

        # A head's joint override turns the jaw 45° about +Y over its clip's pose.
        turn = {"Jaw": crowdmorph.JointTransform(rotation=[0, 0.38268343, 0, 0.9238795])}
        heads = [crowdmorph.Head(1, rig, "yaw", 0), crowdmorph.Head(2, rig, "yaw", 0, joints=turn)]
        frame = client.crowd_frame(heads, format="f32")
        assert list(frame.heads.buffer_indices) == [0, 1]
        r = math.sqrt(0.5)
        assert _close(_vertices(frame, 0), rest)
        assert _close(_vertices(frame, 1), [(0, 0, 0), (r, 0, -r), (0, 1, 0)])

        # Back to the defaults: the clip keeps its joint table, and a new upload's HeadYaw,
        # which no joint of this rig takes now, is reported, not refused.
        reset = client.reset_joint_map(rig)
        assert (reset.rig, reset.default, reset.channels) == (rig, True, [])
        assert client.joint_map(rig) == reset
        frame = client.crowd_frame([(2, rig, "yaw", 1)], format="f32")
        assert _close(_vertices(frame, 0), [(0, 0, 0), (1, 1 - c, -s), (0, 1, 0)])
        up = client.upload_clip(rig, _csv(["a", "HeadYaw"], [[0, 0.5]]), name="after")
        assert up.ignored == ["HeadYaw"]
    finally:
        client.delete_rig(rig)
    with pytest.raises(crowdmorph.NotFound) as e:
        client.joint_map(rig)
    assert e.value.code == "unknown_rig"


def test_joint_map_arguments_are_checked_before_sending(client):
    with pytest.raises(TypeError):
        client.set_joint_map(RIG, [{"column": "HeadYaw", "node": "Head", "axes": [1, 0, 0]}])
    with pytest.raises(ValueError):
        client.set_joint_map(RIG, [{"column": "HeadYaw", "node": "Head", "axis": [1, 0]}])
    with pytest.raises(ValueError):
        client.set_joint_map(RIG, {"channel": []})
    with pytest.raises(TypeError):
        client.set_joint_map(RIG, "HeadYaw")

"""The decoder and encoder against the protocol's golden files, byte for byte (no server).

``proto/tests/golden/<message>.bincode`` and ``.json`` are what the Rust types write;
``tests/golden/crowd_frame_aligned.bin`` is the server's own aligned encoding of a q16 frame.
Every bincode file must decode to the message its JSON twin describes and encode back to the
same bytes.
"""

from __future__ import annotations

import json
import math
import struct

import pytest

import crowdmorph
from crowdmorph import arrays, messages, wire
from crowdmorph.results import CrowdFrame
from conftest import ALIGNED_GOLDEN, PROTO_GOLDEN
from _util import f32, flat, norm_floats

# Every bincode golden file and the message class it holds.
GOLDEN = {
    "crowd_frame_request": messages.CrowdFrameRequest,
    "crowd_frame_request_animated": messages.CrowdFrameRequest,
    "crowd_frame_request_layered": messages.CrowdFrameRequest,
    "crowd_frame_response": messages.CrowdFrameResponse,
    "crowd_frame_response_q16r": messages.CrowdFrameResponse,
    "crowd_pose_response": messages.CrowdPoseResponse,
    "rig_channels": messages.RigChannels,
    "rig_info": messages.RigInfo,
    "rig_list": messages.RigList,
    "lod_info": messages.LodInfo,
    "lod_request": messages.LodRequest,
    "mesh_response": messages.MeshResponse,
    "clip_upload": messages.ClipUpload,
    "clip_list": messages.ClipList,
    "render_request": messages.RenderRequest,
    "session_request": messages.SessionRequest,
    "session_patch": messages.SessionPatch,
    "session_info": messages.SessionInfo,
    "motion_graph": messages.MotionGraph,
    "graph_list": messages.GraphList,
    "live_input": messages.LiveInput,
    "live_ack": messages.LiveAck,
    "mapping": messages.MappingSpec,
}


# The stream's binary messages: an enum, whose JSON (serde's) wraps the message in its variant.
STREAM_GOLDEN = {
    "stream_vertices": "Vertices",
    "stream_frame": "Frame",
    "stream_delta_keyframes": "Delta",
    "stream_delta_residuals": "Delta",
    "stream_packed_deflate": "Packed",
    "stream_layers": "Layers",
    "stream_poses": "Poses",
}


def test_every_golden_bincode_file_has_a_python_message():
    found = {p.stem for p in PROTO_GOLDEN.glob("*.bincode")} - set(STREAM_GOLDEN)
    assert found, f"no golden files in {PROTO_GOLDEN}"
    assert found == set(GOLDEN), "a golden file without a Python message, or the reverse"


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_bincode_decodes_to_its_json_and_encodes_back(name):
    raw = (PROTO_GOLDEN / f"{name}.bincode").read_bytes()
    want = json.loads((PROTO_GOLDEN / f"{name}.json").read_bytes())
    msg = wire.decode(GOLDEN[name], raw)
    assert norm_floats(messages.as_dict(msg)) == norm_floats(want)
    assert wire.encode(msg) == raw


@pytest.mark.parametrize("name", sorted(STREAM_GOLDEN))
def test_golden_stream_messages_decode_to_their_json_and_encode_back(name):
    raw = (PROTO_GOLDEN / f"{name}.bincode").read_bytes()
    want = json.loads((PROTO_GOLDEN / f"{name}.json").read_bytes())[STREAM_GOLDEN[name]]
    msg = wire.decode_as(messages.STREAM_MESSAGE, raw)
    assert norm_floats(messages.as_dict(msg)) == norm_floats(want)
    assert wire.encode_as(messages.STREAM_MESSAGE, msg) == raw


def test_a_framing_camera_is_json_only():
    # JSON: as the server writes it, the frame in place of position and target; absent when
    # there is none, so the other cameras' JSON (and the golden files) stay as they were.
    framed = messages.CameraSpec(frame="faces")
    assert messages.as_dict(framed) == {
        "position": None,
        "target": None,
        "fov_y": 30.0,
        "near": None,
        "far": None,
        "frame": "faces",
    }
    looking = messages.CameraSpec([0, 0, 5], [0, 0, 0])
    assert "frame" not in messages.as_dict(looking)
    # Bincode: the frame takes no bytes (the layout is pinned), and a camera without a
    # position cannot be written.
    raw = wire.encode(looking)
    assert len(raw) == 4 * 7 + 2
    assert wire.encode(messages.CameraSpec([0, 0, 5], [0, 0, 0], frame="bodies")) == raw
    assert wire.decode(messages.CameraSpec, raw) == looking
    with pytest.raises(ValueError, match="JSON"):
        wire.encode(framed)
    # Heads in every form a crowd takes become Head objects for a JSON body.
    h = messages.as_head((1, "r", "talk", 3))
    assert (h.head, h.rig, h.clip, h.frame, h.lod) == (1, "r", "talk", 3, 0)
    h = messages.as_head({"head": 2, "rig": "r", "blend": [("talk", 1, 0.5)]})
    assert h.blend == [messages.BlendLayer("talk", 1, 0.5)]
    assert messages.as_dict(h)["blend"] == [{"clip": "talk", "frame": 1, "t": 0.5}]


def test_the_worked_example_request_is_built_from_python_values():
    # proto/README.md's worked example: two heads of talk, f16, wrap.
    req = messages.CrowdFrameRequest(
        heads=[
            messages.Head(7, "default-head", "talk", 12),
            messages.Head(300, "default-head", "talk", -1, lod=2),
        ],
        output=messages.OutputOptions(normals=False, format="f16"),
        wrap=True,
    )
    raw = (PROTO_GOLDEN / "crowd_frame_request.bincode").read_bytes()
    assert len(raw) == 64
    assert wire.encode(req) == raw
    # Each head ends in eight zero bytes: blend = [], weights = None, joints = [], layers = [],
    # weights_mode = override, clamp = None, mapping = None, tolerance = None.
    assert raw[: 1 + 1 + 13 + 5 + 1 + 1 + 8].endswith(b"\x18\x00" + b"\x00" * 8)
    # The fast writer takes tuples and dicts to the same bytes.
    tuples = messages.CrowdFrameRequest(
        heads=[(7, "default-head", "talk", 12), {"head": 300, "rig": "default-head",
                                                 "clip": "talk", "frame": -1, "lod": 2}],
        output=messages.OutputOptions(normals=False, format="f16"),
    )
    assert wire.encode(tuples) == raw


def test_layers_of_a_crowd_head_decode_and_encode_like_the_rust_types():
    raw = (PROTO_GOLDEN / "crowd_frame_request_layered.bincode").read_bytes()
    req = wire.decode(messages.CrowdFrameRequest, raw)
    (h,) = req.heads
    assert [x.clip for x in h.layers] == ["smile", "surprise", "talk"]
    assert h.layers[0].mask == "lower_face"
    assert h.layers[1].mask == {"eyeBlinkLeft": 0.75} and h.layers[1].reference == 0
    assert h.layers[1].mode == "additive"
    assert h.layers[2].mask == ["jawOpen"] and h.layers[2].joint_mask == ["Head"]
    assert (h.weights_mode, h.clamp, h.mapping) == ("additive", [0.0, 1.0], "arkit")
    assert h.tolerance == pytest.approx(0.002)
    layers = [
        {"clip": "smile", "frame": 5, "weight": 0.5, "mask": "lower_face"},
        {"clip": "surprise", "frame": 20, "mode": "additive", "reference": 0,
         "mask": {"eyeBlinkLeft": 0.75}},
        messages.Layer("talk", -1, 0.25, mask=["jawOpen"], joint_mask=["Head"]),
    ]
    head = messages.Head(11, "default-head", "talk", 3, weights={"jawOpen": 0.5},
                         layers=layers, weights_mode="additive", clamp=[0, 1],
                         mapping="arkit", tolerance=0.002)
    assert wire.encode(messages.CrowdFrameRequest([head])) == raw
    as_dict = {"head": 11, "rig": "default-head", "clip": "talk", "frame": 3,
               "weights": {"jawOpen": 0.5}, "layers": layers, "weights_mode": "additive",
               "clamp": [0, 1], "mapping": "arkit", "tolerance": 0.002}
    assert wire.encode(messages.CrowdFrameRequest([as_dict])) == raw
    want = json.loads((PROTO_GOLDEN / "crowd_frame_request_layered.json").read_bytes())
    assert messages.as_dict(head)["layers"] == want["heads"][0]["layers"]


LEFT_EYE = {"LeftEye": messages.JointTransform(rotation=[0.0, 0.5, 0.0, 1.0])}


def test_joint_overrides_of_a_crowd_head_decode_and_encode_like_the_rust_types():
    raw = (PROTO_GOLDEN / "crowd_frame_request_animated.bincode").read_bytes()
    req = wire.decode(messages.CrowdFrameRequest, raw)
    assert [h.head for h in req.heads] == [8, 9, 10]
    assert req.heads[0].joints == LEFT_EYE
    assert [h.joints for h in req.heads[1:]] == [{}, {}]
    # The same request from Python values, joints given as a dict of dicts (what JSON
    # spells), gives the same bytes, through the Head objects and through plain dicts.
    joints = {"LeftEye": {"rotation": [0, 0.5, 0, 1]}}
    heads = [
        messages.Head(8, "default-head", "talk", 40, blend=[("smile", 3, 0.25)], joints=joints),
        messages.Head(9, "default-head", weights={"jawOpen": 0.5, "eyeBlinkLeft": 1.0}),
        messages.Head(10, "default-head", weights=[0.0, 0.5]),
    ]
    assert heads[0].joints == LEFT_EYE
    assert wire.encode(messages.CrowdFrameRequest(heads)) == raw
    as_dicts = [
        {"head": 8, "rig": "default-head", "clip": "talk", "frame": 40,
         "blend": [{"clip": "smile", "frame": 3, "t": 0.25}], "joints": joints},
        {"head": 9, "rig": "default-head", "weights": {"jawOpen": 0.5, "eyeBlinkLeft": 1.0}},
        {"head": 10, "rig": "default-head", "weights": [0.0, 0.5]},
    ]
    assert wire.encode(messages.CrowdFrameRequest(as_dicts)) == raw
    # The joints' bytes: one entry, "LeftEye", None, Some([0, 0.5, 0, 1]), None.
    entry = b"\x01\x07LeftEye\x00\x01" + struct.pack("<4f", 0, 0.5, 0, 1) + b"\x00"
    assert entry in raw
    # JSON: an object by node name with all three keys, as the server writes it.
    want = json.loads((PROTO_GOLDEN / "crowd_frame_request_animated.json").read_bytes())
    assert messages.as_dict(heads[0])["joints"] == want["heads"][0]["joints"]
    assert messages.as_dict(heads[1])["joints"] == {}


def test_joint_overrides_of_session_heads_and_changes_decode_and_encode_like_the_rust_types():
    def session_head(head, clip, offset, x, **kw):
        return messages.SessionHead(head, "default-head", clip, offset, [x, 0.0, -1.5], 15.0,
                                    1.0, **kw)

    raw = (PROTO_GOLDEN / "session_request.bincode").read_bytes()
    req = wire.decode(messages.SessionRequest, raw)
    assert [h.joints for h in req.heads[:3]] == [{}, {}, {}]
    eye = messages.JointTransform(translation=[0.0, 0.0, 0.25], rotation=[0.0, 0.5, 0.0, 1.0])
    assert req.heads[3].joints == {"LeftEye": eye}
    graph = messages.GraphPlay("moods", "talk", 7, ["smile"])
    mine = messages.SessionRequest(
        heads=[
            session_head(1, "talk", 0, 0.0),
            session_head(2, "talk", 0, 0.5),
            session_head(3, "smile", -4, 1.0,
                         layers=[{"clip": "talk", "frame": 2, "weight": 0.5,
                                  "mask": "lower_face"}],
                         clamp=[0.0, 1.0],
                         live={"hold_ms": 750, "mapping": "a2f",
                               "smoothing": {"min_cutoff": 1.0, "beta": 0.5}}),
            session_head(4, "", 0, 1.5, graph=graph,
                         joints=[("LeftEye", {"translation": [0, 0, 0.25],
                                              "rotation": [0, 0.5, 0, 1]})]),
            session_head(5, "", 0, 2.0,
                         alive={"blink": True, "saccades": True, "look_at": [0.5, 1.5, 2.0],
                                "seed": 42}),
        ],
        alive=messages.Alive(blink=True, breathing=True),
    )
    assert mine == req
    assert wire.encode(mine) == raw

    raw = (PROTO_GOLDEN / "session_patch.bincode").read_bytes()
    patch = wire.decode(messages.SessionPatch, raw)
    head_turn = {"Head": messages.JointTransform(rotation=[0.0, 0.5, 0.0, 1.0])}
    assert patch.change[0].joints == head_turn
    assert patch.change[1].joints is None  # unchanged
    assert patch.add[0].joints == {}
    mine = messages.SessionPatch(
        remove=[2],
        change=[
            messages.HeadChange(3, clip="talk", yaw=-30.0,
                                joints={"Head": {"rotation": [0, 0.5, 0, 1]}},
                                layers=[], clamp=[-1.0, 2.0], live=messages.LiveSpec(),
                                alive={}),
            messages.HeadChange(4, node="surprise"),
        ],
        add=[session_head(9, "idle", 7, 2.0)],
        alive={"look_at": [3.0, 1.5, -4.0]},
    )
    assert mine == patch
    assert wire.encode(mine) == raw
    # None leaves a head's overrides; {} clears them: Some(empty).
    w = wire.Writer()
    wire.Msg(messages.HeadChange).write(w, messages.HeadChange(4, joints={}))
    # (then layers = None, clamp = None, live = None, alive = None)
    assert bytes(w.out) == b"\x04" + b"\x00" * 6 + b"\x01\x00" + b"\x00\x00\x00\x00"
    assert messages.as_dict(messages.HeadChange(4, joints={}))["joints"] == {}
    assert messages.as_dict(messages.HeadChange(4))["joints"] is None


def test_bad_joint_overrides_are_refused_before_sending():
    with pytest.raises(ValueError, match="twice"):
        messages.Head(1, "r", joints=[("Jaw", {}), ("Jaw", {})])
    with pytest.raises(TypeError):
        messages.Head(1, "r", joints={"Jaw": {"rotate": [0, 0, 0, 1]}})
    short = messages.Head(1, "r", joints={"Jaw": {"rotation": [0, 1]}})
    with pytest.raises(ValueError, match="expected 4 numbers"):
        wire.encode(messages.CrowdFrameRequest([short]))
    # A node twice in a body is a decode error (a dict holds each name once).
    w = wire.Writer()
    w.varint(2)
    for _ in range(2):
        w.string("Jaw")
        w.out += b"\x00\x00\x00"
    with pytest.raises(wire.DecodeError, match="twice"):
        wire.decode_as(messages.JOINTS, bytes(w.out))


def test_the_worked_example_response_decodes_field_by_field():
    raw = (PROTO_GOLDEN / "crowd_frame_response.bincode").read_bytes()
    assert len(raw) == 61
    r = wire.decode(messages.CrowdFrameResponse, raw)
    assert (r.format, r.normals) == ("f32", False)
    (b,) = r.buffers
    assert (b.rig, b.clip, b.frame, b.lod, b.vertices) == ("tri", "wave", 1, 0, 2)
    assert b.quantization is None and b.normals is None
    assert struct.unpack("<6f", b.positions) == (0.0, 1.0, -2.5, 0.5, 0.25, 3.0)
    assert [(h.head, h.buffer) for h in r.heads] == [(1, 0), (2, 0)]
    assert r.timings == messages.FrameTimings(250, 70000, 71000, 5)


def _walk_aligned(raw: bytes):
    """Reads the aligned golden frame with the primitive reader, field by field as
    proto/README.md lists them, and returns the offsets where the two payloads start."""
    r = wire.Reader(raw)
    assert r.u32() == 2 and r.bool() is True  # format q16, normals
    assert r.length() == 1  # one buffer
    assert (r.string(), r.string(), r.u32(), r.u32(), r.u32()) == ("default-head", "talk", 12, 1, 3)
    assert r.u8() == 1  # Some(quantization)
    r.f32x3(), r.f32x3(), r.f32x3()
    offsets = []
    for tag in (None, 1):  # positions, then Some(normals)
        if tag is not None:
            assert r.u8() == tag
        pad = r.bytes()
        assert len(pad) <= 15 and not any(pad), "pads are 0-15 zero bytes"
        n = r.varint()
        offsets.append(r.pos)
        r.pos += n
    return offsets


def test_the_servers_aligned_frame_decodes_and_its_payloads_sit_on_16_bytes():
    raw = ALIGNED_GOLDEN.read_bytes()
    offsets = _walk_aligned(raw)
    assert all(o % 16 == 0 for o in offsets), offsets
    r = wire.decode(messages.CrowdFrameResponse, raw)
    assert (r.format, r.normals) == ("q16", True)
    (b,) = r.buffers
    assert (b.rig, b.clip, b.frame, b.lod, b.vertices) == ("default-head", "talk", 12, 1, 3)
    q = b.quantization
    assert [round(v, 9) for v in q.min] == [-1.0, -2.0, -0.5]
    assert struct.unpack("<9h", b.positions) == tuple(i * 1000 - 4000 for i in range(9))
    assert struct.unpack("<9h", b.normals) == tuple(i * 3000 for i in range(9))
    assert [(h.head, h.buffer) for h in r.heads] == [(7, 0), (300, 0)]
    assert r.timings == messages.FrameTimings(120, 900, 1500, None)
    # The decoded memoryviews are the body's own bytes at those offsets (no copy).
    assert bytes(b.positions) == raw[offsets[0] : offsets[0] + 18]


def test_the_aligned_frames_q16_payloads_dequantize_as_the_readme_says(backend):
    raw = ALIGNED_GOLDEN.read_bytes()
    frame = CrowdFrame(wire.decode(messages.CrowdFrameResponse, raw), backend)
    b = frame.buffers[0]
    q = b.quantization
    pos = flat(b.positions)
    for i, v in enumerate(pos):
        a = i % 3
        want = q.min[a] + ((i * 1000 - 4000) + 32768) * q.step[a]
        assert math.isclose(v, want, rel_tol=2**-23, abs_tol=1e-7), (i, v, want)
    nrm = flat(b.normals)
    for i, v in enumerate(nrm):
        assert abs(v - (i * 3000) / 32767) <= 2**-24, (i, v)
    # Clones share a buffer; positions(i) is the head's.
    assert frame.positions(1) is b.positions
    if backend == "numpy":
        assert b.positions.shape == (3, 3) and str(b.positions.dtype) == "float32"
    else:
        assert len(b.positions) == 9 and b.positions.typecode == "f"


def test_the_numpy_q16_decoder_matches_the_reference_bit_for_bit():
    np = pytest.importorskip("numpy", reason="numpy is not installed")
    # Boxes arrive as float32, so the test's are float32 values too.
    quant = messages.Quantization(
        min=[f32(-0.123), 1.5, -7.25],
        step=[f32(3.1e-6), f32(2.2e-5), f32(1.7e-4)],
        max_error=[0, 0, 0],
    )
    q = np.arange(-32768, 32768, 7, dtype="<i2")[: (65536 // 7) // 3 * 3]
    got = arrays.decode_positions(q.tobytes(), "q16", quant, "numpy").reshape(-1)
    # The reference, in float32 one operation at a time: min + (q + 32768) * step.
    f = np.float32
    want = [
        f(quant.min[i % 3]) + (f(v) + f(32768.0)) * f(quant.step[i % 3])
        for i, v in enumerate(q.tolist())
    ]
    assert got.tobytes() == np.array(want, dtype=np.float32).tobytes()
    # The pure-Python path computes in double and rounds once: it differs from the float32
    # chain by its two roundings at most, a float32 ulp or two of the box's extent.
    py = np.array(arrays.decode_positions(q.tobytes(), "q16", quant, "python"), dtype=np.float64)
    extent = np.array(
        [abs(quant.min[a]) + 65536 * quant.step[a] for a in range(3)] * (len(py) // 3)
    )
    assert np.all(np.abs(py - got.astype(np.float64)) <= 2**-22 * extent)


@pytest.mark.parametrize(
    "bits, value",
    [(0x3C00, 1.0), (0xC100, -2.5), (0x7BFF, 65504.0), (0x0001, 2.0**-24), (0x8000, -0.0)],
)
def test_f16_components_decode_exactly(bits, value, backend):
    data = struct.pack("<3H", bits, bits, bits)
    out = flat(arrays.decode_positions(data, "f16", None, backend))
    assert out == [value] * 3
    assert math.copysign(1, out[0]) == math.copysign(1, value)


@pytest.mark.parametrize(
    "n, size",
    [
        (0, 1),
        (250, 1),
        (251, 3),
        (65535, 3),
        (65536, 5),
        (2**32 - 1, 5),
        (2**32, 9),
        (2**64 - 1, 9),
    ],
)
def test_varints_take_the_documented_bytes(n, size):
    w = wire.Writer()
    w.varint(n)
    assert len(w.out) == size
    r = wire.Reader(bytes(w.out))
    assert r.varint() == n
    r.finish()


@pytest.mark.parametrize(
    "n, z", [(0, 0), (-1, 1), (1, 2), (-2, 3), (2**63 - 1, 2**64 - 2), (-(2**63), 2**64 - 1)]
)
def test_i64_is_zigzag(n, z):
    w = wire.Writer()
    w.i64(n)
    want = wire.Writer()
    want.varint(z)
    assert w.out == want.out
    assert wire.Reader(bytes(w.out)).i64() == n


def test_truncated_and_trailing_bytes_are_decode_errors():
    raw = (PROTO_GOLDEN / "rig_info.bincode").read_bytes()
    for cut in (1, len(raw) // 2, len(raw) - 1):
        with pytest.raises(wire.DecodeError):
            wire.decode(messages.RigInfo, raw[:cut])
    with pytest.raises(wire.DecodeError, match="1 bytes after the message"):
        wire.decode(messages.RigInfo, raw + b"\x00")


def test_a_huge_declared_length_is_refused_without_allocating():
    w = wire.Writer()
    w.varint(1 << 40)  # a Vec<RigInfo> of 2^40 elements, then nothing
    with pytest.raises(wire.DecodeError, match="more than the 0 bytes left"):
        wire.decode(messages.RigList, bytes(w.out))


def test_an_unknown_format_variant_is_a_decode_error():
    raw = bytearray((PROTO_GOLDEN / "crowd_frame_response.bincode").read_bytes())
    raw[0] = 5  # format: no variant 5 (f32, f16, q16, q16r, weights)
    with pytest.raises(wire.DecodeError, match="variant 5"):
        wire.decode(messages.CrowdFrameResponse, bytes(raw))


def test_error_bodies_become_typed_exceptions():
    body = (PROTO_GOLDEN / "error.json").read_bytes()
    e = crowdmorph.errors.error_from_response(404, body, None, "req-1")
    assert isinstance(e, crowdmorph.NotFound)
    assert (e.status, e.code, e.request_id) == (404, "unknown_rig", "req-1")
    assert e.message == 'no rig "x" (rigs: default-head)'

    busy = b'{"error":{"code":"queue_full","message":"queue full"}}'
    e = crowdmorph.errors.error_from_response(503, busy, "2")
    assert isinstance(e, crowdmorph.Overloaded) and e.retry_after == 2.0

    off = b'{"error":{"code":"render_unavailable","message":"install mesa-vulkan-drivers"}}'
    e = crowdmorph.errors.error_from_response(503, off, None)
    assert isinstance(e, crowdmorph.Unavailable) and not isinstance(e, crowdmorph.Overloaded)
    assert e.retry_after is None

    e = crowdmorph.errors.error_from_response(502, b"<html>Bad Gateway</html>")
    assert isinstance(e, crowdmorph.ServerError)
    assert e.code == "http_502" and "Bad Gateway" in e.message


def test_pose_weights_are_binary16_in_channel_order():
    raw = (PROTO_GOLDEN / "stream_poses.bincode").read_bytes()
    msg = wire.decode_as(messages.STREAM_MESSAGE, raw)
    assert isinstance(msg, messages.TickPoses)
    (pose,) = msg.poses
    assert pose.weights_f32() == [0.5, 1.0, -0.25]
    (node,) = pose.joints
    assert node.node == 2 and node.translation == [0.0, 0.25, 0.0] and node.scale is None
    assert list(msg.heads.buffer_indices) == [messages.HEAD_UNCHANGED, 0, messages.HEAD_MISSING]
    resp = wire.decode(
        messages.CrowdPoseResponse, (PROTO_GOLDEN / "crowd_pose_response.bincode").read_bytes()
    )
    assert resp.format == "weights"
    assert [p.weights_f32() for p in resp.poses] == [[0.5, 1.0, -0.25], [0.0, 0.0, 0.125]]

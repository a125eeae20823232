"""The v1 messages, field for field as ``proto/README.md`` lists them.

Each class is a dataclass whose ``@wire(...)`` declaration gives its bincode layout: the fields
in wire order with their types. Field names are the protocol's (and its JSON's). Enums are the
lowercase variant names as strings (``"f32"``, ``"q16"``, ``"png"``...). ``Blob`` payloads are
``memoryview`` slices of the response body in decoded messages; any bytes-like object is
accepted when encoding.

These are the raw wire messages; :mod:`crowdmorph.results` turns payloads into arrays.
"""

from __future__ import annotations

import base64
import dataclasses
import operator
import struct
from array import array
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Union, overload

from .wire import (
    BLOB,
    BOOL,
    F32,
    F64,
    F32X3,
    F32X4,
    I64,
    STR,
    U8,
    U8X3,
    U32,
    U64,
    VAR16,
    VAR32,
    DecodeError,
    Enum,
    Msg,
    Opt,
    Reader,
    Tagged,
    Vec,
    Writer,
    decode_as,
    wire,
)

__all__ = [
    "FORMATS",
    "IMAGE_FORMATS",
    "CAMERA_FRAMES",
    "Head",
    "as_head",
    "BlendLayer",
    "JointTransform",
    "OutputOptions",
    "CrowdFrameRequest",
    "Quantization",
    "FrameBuffer",
    "HeadBuffer",
    "HeadBuffers",
    "FrameTimings",
    "CrowdFrameResponse",
    "Memory",
    "Aabb",
    "ClipInfo",
    "PrimitiveInfo",
    "LodLevelInfo",
    "LodInfo",
    "RigInfo",
    "RigList",
    "LodLevelRequest",
    "LodRequest",
    "MeshPrimitive",
    "MeshResponse",
    "ClipUpload",
    "ClipList",
    "JointChannelSpec",
    "JointMapSpec",
    "JointMapInfo",
    "Readiness",
    "Placement",
    "CameraSpec",
    "ImageOptions",
    "RenderRequest",
    "GraphPlay",
    "GraphNode",
    "GraphEdge",
    "MotionGraph",
    "GraphInfo",
    "GraphList",
    "BuiltGraph",
    "Alive",
    "SessionHead",
    "SessionRequest",
    "SessionStats",
    "SessionInfo",
    "SessionList",
    "HeadChange",
    "SessionPatch",
    "TickVertices",
    "TickFrame",
    "TickDelta",
    "PackedMessage",
    "TickLayers",
    "HeadLayers",
    "NodePose",
    "HeadPose",
    "CrowdPoseResponse",
    "RigChannels",
    "TickPoses",
    "MESSAGE_ENCODINGS",
    "MAX_UNPACKED_BYTES",
    "STREAM_MESSAGE",
    "HEAD_UNCHANGED",
    "HEAD_MISSING",
    "decode_stream_message",
    "unpack_stream_message",
    "as_dict",
]

#: Crowd-frame formats by bincode variant index: the vertex formats, then ``weights`` (no
#: vertices: each head's pose, answered with a :class:`CrowdPoseResponse`).
FORMATS = ("f32", "f16", "q16", "q16r", "weights")
#: Image formats of rendered frames by bincode variant index.
IMAGE_FORMATS = ("png", "jpeg", "rgba")
#: Compressions of packed stream messages (``MessageEncoding``) by bincode variant index.
MESSAGE_ENCODINGS = ("zstd", "deflate")

FORMAT = Enum(*FORMATS)
IMAGE_FORMAT = Enum(*IMAGE_FORMATS)
MESSAGE_ENCODING = Enum(*MESSAGE_ENCODINGS)


# ---------------------------------------------------------------------------------------------
# Crowd frames.


@wire(("clip", STR), ("frame", I64), ("t", F32))
@dataclass
class BlendLayer:
    """One blend layer of a head: fraction ``t`` (0–1) of ``frame`` of ``clip``."""

    clip: str
    frame: int
    t: float


class _LiveWeights:
    """``LiveWeights``: a dict of weights by target name (bincode variant 0, ``Vec<(String,
    f32)>``) or a sequence of one weight per ``RigInfo.targets`` name (variant 1,
    ``Vec<f32>``)."""

    def read(self, r: Reader) -> Any:
        at = r.pos
        i = r.u32()
        if i == 0:
            return {r.string(): r.f32() for _ in range(r.length())}
        if i == 1:
            return [r.f32() for _ in range(r.length())]
        raise DecodeError(f"variant {i} of LiveWeights does not exist", at)

    def write(self, w: Writer, v: Any) -> None:
        if isinstance(v, Mapping):
            w.varint(0)
            w.varint(len(v))
            for name, x in v.items():
                w.string(name)
                w.f32(float(x))
        else:
            xs = list(v)
            w.varint(1)
            w.varint(len(xs))
            for x in xs:
                w.f32(float(x))


LIVE_WEIGHTS = _LiveWeights()
_BLEND = Vec(Msg(BlendLayer))
_WEIGHTS = Opt(LIVE_WEIGHTS)


@wire(("translation", Opt(F32X3)), ("rotation", Opt(F32X4)), ("scale", Opt(F32X3)))
@dataclass
class JointTransform:
    """A skeleton node's local transform, or part of it (what a glTF animation channel sets):
    ``translation`` (rig units), ``rotation`` (quaternion x, y, z, w; normalized by the server,
    not zero) and ``scale`` per axis. Each component given replaces what the head's clip, blend
    or rest pose gives the node; ``None`` keeps it."""

    translation: Optional[Sequence[float]] = None
    rotation: Optional[Sequence[float]] = None
    scale: Optional[Sequence[float]] = None


#: What ``joints`` accepts: a dict by node name of :class:`JointTransform` objects or dicts
#: with their keys (``{"LeftEye": {"rotation": [0, 0.17, 0, 0.985]}}``), or ``(name,
#: transform)`` pairs.
JointsLike = Union[
    Mapping[str, Union[JointTransform, Mapping[str, Any]]],
    Iterable[Sequence[Any]],
]


def _joint_transform(t: Any) -> JointTransform:
    """A :class:`JointTransform` from itself or a dict with its keys (missing ones are
    ``None``, as the server reads them; others are an error, as there)."""
    if isinstance(t, JointTransform):
        return t
    if isinstance(t, Mapping):
        return JointTransform(**t)
    raise TypeError(f"a joint transform is a JointTransform or a dict, not {type(t).__name__}")


def joint_overrides(joints: Optional[JointsLike]) -> Dict[str, JointTransform]:
    """``JointOverrides`` as the client holds them: a dict of :class:`JointTransform` by node
    name, in the order given (the wire order). ``None`` is no overrides; a node named twice is
    a :class:`ValueError` (the server refuses it too)."""
    if joints is None:
        return {}
    if type(joints) is dict and all(type(t) is JointTransform for t in joints.values()):
        return joints
    items = joints.items() if isinstance(joints, Mapping) else joints
    out: Dict[str, JointTransform] = {}
    for name, t in items:
        if not isinstance(name, str):
            raise TypeError(f"a joint override's node name is a string, not {name!r}")
        if name in out:
            raise ValueError(f"node {name!r} is overridden twice")
        out[name] = _joint_transform(t)
    return out


class _JointOverrides:
    """``JointOverrides``: in JSON an object by node name; in bincode ``Vec<(String,
    JointTransform)>`` (a varint count, then each node's name and transform). Python sees a
    dict of :class:`JointTransform` by node name."""

    def read(self, r: Reader) -> Dict[str, JointTransform]:
        out: Dict[str, JointTransform] = {}
        for _ in range(r.length()):
            at = r.pos
            name = r.string()
            if name in out:
                # A dict cannot hold it, and no server sends it (it refuses such requests).
                raise DecodeError(f"joint override of node {name!r} twice", at)
            out[name] = _JOINT_TRANSFORM.read(r)
        return out

    def write(self, w: Writer, v: Optional[JointsLike]) -> None:
        joints = joint_overrides(v)
        w.varint(len(joints))
        for name, t in joints.items():
            w.string(name)
            _JOINT_TRANSFORM.write(w, t)


_JOINT_TRANSFORM = Msg(JointTransform)
JOINTS = _JointOverrides()


class _Mask:
    """A layer's ``Mask``: a list of target names (bincode variant 0), a dict of names to
    weights in [0, 1] (variant 1), or a built-in mask's name such as ``"lower_face"`` (variant
    2)."""

    def read(self, r: Reader) -> Any:
        at = r.pos
        i = r.u32()
        if i == 0:
            return [r.string() for _ in range(r.length())]
        if i == 1:
            return {r.string(): r.f32() for _ in range(r.length())}
        if i == 2:
            return r.string()
        raise DecodeError(f"variant {i} of Mask does not exist", at)

    def write(self, w: Writer, v: Any) -> None:
        if isinstance(v, str):
            w.varint(2)
            w.string(v)
        elif isinstance(v, Mapping):
            w.varint(1)
            w.varint(len(v))
            for name, x in v.items():
                w.string(name)
                w.f32(float(x))
        else:
            names = list(v)
            w.varint(0)
            w.varint(len(names))
            for name in names:
                w.string(name)


LAYER_MODE = Enum("override", "additive")


@wire(
    ("clip", STR),
    ("frame", I64),
    ("weight", F32),
    ("mode", LAYER_MODE),
    ("mask", Opt(_Mask())),
    ("reference", Opt(I64)),
    ("joint_mask", Opt(Vec(STR))),
)
@dataclass
class Layer:
    """One layer over a head's base pose: ``frame`` of ``clip`` applied by ``weight`` to the
    targets ``mask`` selects (all without one), by ``mode`` ``"override"`` (w ← (1 − a)·w +
    a·layer) or ``"additive"`` (w ← w + a·(layer − reference), the reference a frame of the
    same clip or the neutral); on a skinned rig also to the joints ``joint_mask`` names (all
    the clip animates without one). ``proto/README.md``, "Layers and masks"."""

    clip: str
    frame: int = 0
    weight: float = 1.0
    mode: str = "override"
    mask: Optional[Union[Sequence[str], Mapping[str, float], str]] = None
    reference: Optional[int] = None
    joint_mask: Optional[Sequence[str]] = None


_LAYERS = Vec(Msg(Layer))
_MAPPING = Opt(STR)
_TOLERANCE = Opt(F32)
class _Clamp:
    """``Option<[f32; 2]>``: a fixed pair, no length."""

    def read(self, r: Reader) -> Any:
        at = r.pos
        tag = r.u8()
        if tag == 0:
            return None
        if tag == 1:
            return [r.f32(), r.f32()]
        raise DecodeError(f"option tag is {tag}, not 0 or 1", at)

    def write(self, w: Writer, v: Any) -> None:
        if v is None:
            w.out.append(0)
            return
        lo, hi = v
        w.out.append(1)
        w.f32(float(lo))
        w.f32(float(hi))


CLAMP = _Clamp()


def _of_head_layer(x: Any) -> Layer:
    """A :class:`Layer` from itself or a dict with its keys."""
    if isinstance(x, Layer):
        return x
    if isinstance(x, Mapping):
        return Layer(**x)
    raise TypeError(f"a layer is a Layer or a dict, not {type(x).__name__}")


@wire(
    ("head", U64),
    ("rig", STR),
    ("clip", STR),
    ("frame", I64),
    ("lod", U32),
    ("blend", _BLEND),
    ("weights", _WEIGHTS),
    ("joints", JOINTS),
    ("layers", _LAYERS),
    ("weights_mode", LAYER_MODE),
    ("clamp", CLAMP),
    ("mapping", _MAPPING),
    ("tolerance", _TOLERANCE),
)
@dataclass
class Head:
    """One head of a crowd: the client's id (echoed), which rig plays which clip at which frame
    (wrapping past the end when the request's ``wrap`` is true) and level of detail; optionally
    up to four ``blend`` layers over that frame (weights = (1 − Σt)·clip[frame] + Σ tᵢ·layerᵢ),
    or live ``weights`` instead of a clip (a dict by target name, or one per
    ``RigInfo.targets`` name); and, on a rig with a skeleton, ``joints``: local transforms of
    named nodes over that pose (``{"LeftEye": JointTransform(rotation=[0, 0.17, 0, 0.985])}``;
    dicts with :class:`JointTransform`'s keys work too). Up to eight ``layers``
    (:class:`Layer` or dicts) go over that pose in order; ``weights`` sent with a ``clip``
    replace the targets they name (``weights_mode="additive"``: are added), after the layers;
    ``clamp`` (``[lo, hi]``) bounds every final weight. ``mapping`` names a mapping of the rig
    (``"arkit"``, ``"a2f"``, ``"oculus-visemes"``, ``"vrm"`` or one of its own) that named
    ``weights`` go through first: their names are the mapping's sources. ``tolerance`` (a
    fraction of the rig's diagonal, 0..=0.1) lets the server round the head's final weights
    so that heads whose poses differ by less share one job (near-clones)."""

    head: int
    rig: str
    clip: str = ""
    frame: int = 0
    lod: int = 0
    blend: List[BlendLayer] = field(default_factory=list)
    weights: Optional[Union[Mapping[str, float], Sequence[float]]] = None
    joints: Dict[str, JointTransform] = field(default_factory=dict)
    layers: List[Layer] = field(default_factory=list)
    weights_mode: str = "override"
    clamp: Optional[Sequence[float]] = None
    mapping: Optional[str] = None
    tolerance: Optional[float] = None

    def __post_init__(self) -> None:
        j = self.joints
        if type(j) is not dict or j:
            self.joints = joint_overrides(j)
        if self.layers and any(type(x) is not Layer for x in self.layers):
            self.layers = [_of_head_layer(x) for x in self.layers]


@wire(("normals", BOOL), ("format", FORMAT))
@dataclass
class OutputOptions:
    """What the buffers of a crowd frame contain."""

    normals: bool = False
    format: str = "f32"


class _HeadVec:
    """``Vec<Head>`` with a fast writer: a crowd request can carry 100,000 heads, and the
    generic per-field path spends microseconds on each. Items may be :class:`Head` objects,
    ``(head, rig, clip, frame[, lod])`` tuples or dicts with those keys (and optionally
    ``blend``, ``weights`` and ``joints``)."""

    def read(self, r: Reader) -> List[Head]:
        return Vec(Msg(Head)).read(r)

    def write(self, w: Writer, heads: Iterable[Any]) -> None:
        items = heads if isinstance(heads, (list, tuple)) else list(heads)
        out = w.out
        varint = w.varint
        var16 = VAR16.pack
        var32 = VAR32.pack
        w.varint(len(items))
        # Rig and clip names repeat across a crowd: encode each once.
        names: dict = {}
        for h in items:
            blend: Any = ()
            weights: Any = None
            joints: Any = None
            layers: Any = ()
            weights_mode: Any = "override"
            clamp: Any = None
            mapping: Any = None
            tolerance: Any = None
            if type(h) is Head:
                hid, rig, clip, frame, lod = h.head, h.rig, h.clip, h.frame, h.lod
                blend, weights, joints = h.blend, h.weights, h.joints
                layers, weights_mode, clamp = h.layers, h.weights_mode, h.clamp
                mapping, tolerance = h.mapping, h.tolerance
            elif isinstance(h, (tuple, list)):
                if len(h) == 4:
                    hid, rig, clip, frame = h
                    lod = 0
                else:
                    hid, rig, clip, frame, lod = h
            elif isinstance(h, Mapping):
                hid, rig = h["head"], h["rig"]
                clip, frame, lod = h.get("clip", ""), h.get("frame", 0), h.get("lod", 0)
                blend, weights = h.get("blend", ()), h.get("weights")
                joints = h.get("joints")
                layers, clamp = h.get("layers", ()), h.get("clamp")
                weights_mode = h.get("weights_mode", "override")
                mapping, tolerance = h.get("mapping"), h.get("tolerance")
            elif isinstance(h, Head):
                hid, rig, clip, frame, lod = h.head, h.rig, h.clip, h.frame, h.lod
                blend, weights, joints = h.blend, h.weights, h.joints
                layers, weights_mode, clamp = h.layers, h.weights_mode, h.clamp
                mapping, tolerance = h.mapping, h.tolerance
            else:
                raise TypeError(
                    "a head is a Head, a dict or a (head, rig, clip, frame[, lod]) tuple, "
                    f"not {type(h).__name__}"
                )
            if type(hid) is int and 0 <= hid < 251:
                out.append(hid)
            elif type(hid) is int and 0 <= hid <= 0xFFFF:
                out += var16(251, hid)
            elif type(hid) is int and 0 <= hid <= 0xFFFF_FFFF:
                out += var32(252, hid)
            else:
                varint(operator.index(hid))
            for name in (rig, clip):
                enc = names.get(name)
                if enc is None:
                    if not isinstance(name, str):
                        raise TypeError(f"rig and clip are strings, not {type(name).__name__}")
                    sub = Writer()
                    sub.string(name)
                    enc = names[name] = bytes(sub.out)
                out += enc
            frame = operator.index(frame)
            if not -(1 << 63) <= frame < (1 << 63):
                raise ValueError(f"frame {frame} does not fit an i64")
            z = (frame << 1) ^ (frame >> 63)
            if z < 251:
                out.append(z)
            elif z <= 0xFFFF:
                out += var16(251, z)
            else:
                varint(z)
            if type(lod) is int and 0 <= lod < 251:
                out.append(lod)
            else:
                w.u32(operator.index(lod))
            if not blend and weights is None and not joints:
                out += b"\x00\x00\x00"  # blend = [], weights = None, joints = []
            else:
                _BLEND.write(w, [_of_layer(b) for b in blend])
                _WEIGHTS.write(w, weights)
                JOINTS.write(w, joints)
            if not layers and weights_mode == "override" and clamp is None:
                out += b"\x00\x00\x00"  # layers = [], weights_mode = override, clamp = None
            else:
                _LAYERS.write(w, [_of_head_layer(x) for x in layers])
                LAYER_MODE.write(w, weights_mode)
                CLAMP.write(w, clamp)
            if mapping is None:
                out.append(0)  # mapping = None
            else:
                _MAPPING.write(w, mapping)
            if tolerance is None:
                out.append(0)  # tolerance = None
            else:
                _TOLERANCE.write(w, tolerance)


def _of_layer(b: Any) -> BlendLayer:
    """A blend layer from a :class:`BlendLayer`, a dict or a ``(clip, frame, t)`` tuple."""
    if isinstance(b, BlendLayer):
        return b
    if isinstance(b, Mapping):
        return BlendLayer(b["clip"], b.get("frame", 0), b["t"])
    clip, frame, t = b
    return BlendLayer(clip, frame, t)


HEADS = _HeadVec()


def as_head(h: Any) -> Head:
    """A :class:`Head` from any form a crowd accepts (a :class:`Head`, a dict with its keys or
    a ``(head, rig, clip, frame[, lod])`` tuple), its blend layers made :class:`BlendLayer`
    objects: what a JSON body needs, where the bincode writer reads the forms directly."""
    if isinstance(h, Head):
        head = h
    elif isinstance(h, (tuple, list)):
        head = Head(*h)
    elif isinstance(h, Mapping):
        head = Head(**h)
    else:
        raise TypeError(
            "a head is a Head, a dict or a (head, rig, clip, frame[, lod]) tuple, "
            f"not {type(h).__name__}"
        )
    if any(not isinstance(b, BlendLayer) for b in head.blend):
        head = dataclasses.replace(head, blend=[_of_layer(b) for b in head.blend])
    return head


@wire(("heads", HEADS), ("output", Msg(OutputOptions)), ("wrap", BOOL))
@dataclass
class CrowdFrameRequest:
    """``POST /v1/crowd/frame`` request."""

    heads: List[Head]
    output: OutputOptions = field(default_factory=OutputOptions)
    wrap: bool = True


@wire(("min", F32X3), ("step", F32X3), ("max_error", F32X3))
@dataclass
class Quantization:
    """How q16 positions map back to rig space: ``x = min[a] + (q + 32768) * step[a]``."""

    min: List[float]
    step: List[float]
    max_error: List[float]


@wire(
    ("rig", STR),
    ("clip", STR),
    ("frame", U32),
    ("lod", U32),
    ("vertices", U32),
    ("quantization", Opt(Msg(Quantization))),
    ("positions", BLOB),
    ("normals", Opt(BLOB)),
)
@dataclass
class FrameBuffer:
    """One unique blended buffer of a crowd frame (payloads still encoded)."""

    rig: str
    clip: str
    frame: int
    lod: int
    vertices: int
    quantization: Optional[Quantization]
    positions: Any
    normals: Optional[Any]


@wire(("head", U64), ("buffer", U32))
@dataclass
class HeadBuffer:
    """Which buffer (index into ``buffers``) a request head uses."""

    head: int
    buffer: int


_U32_CODE = "I" if array("I").itemsize == 4 else "L"


class HeadBuffers(Sequence):
    """The ``heads`` of a crowd frame: a read-only list of :class:`HeadBuffer`, stored as two
    arrays, ``head_ids`` (``array('Q')``) and ``buffer_indices`` (4-byte unsigned), because a
    frame can have 100,000 heads and objects for each would cost more than the decoding."""

    __slots__ = ("head_ids", "buffer_indices")

    def __init__(self, head_ids: Iterable[int] = (), buffer_indices: Iterable[int] = ()):
        self.head_ids = array("Q", head_ids)
        self.buffer_indices = array(_U32_CODE, buffer_indices)
        if len(self.head_ids) != len(self.buffer_indices):
            raise ValueError("head_ids and buffer_indices differ in length")

    def __len__(self) -> int:
        return len(self.head_ids)

    @overload
    def __getitem__(self, i: int) -> HeadBuffer: ...

    @overload
    def __getitem__(self, i: slice) -> List[HeadBuffer]: ...

    def __getitem__(self, i: Union[int, slice]) -> Any:
        if isinstance(i, slice):
            return [HeadBuffer(h, b) for h, b in zip(self.head_ids[i], self.buffer_indices[i])]
        return HeadBuffer(self.head_ids[i], self.buffer_indices[i])

    def __iter__(self) -> Iterator[HeadBuffer]:
        for h, b in zip(self.head_ids, self.buffer_indices):
            yield HeadBuffer(h, b)

    def __eq__(self, other: object) -> bool:
        if isinstance(other, HeadBuffers):
            return self.head_ids == other.head_ids and self.buffer_indices == other.buffer_indices
        if isinstance(other, (list, tuple)):
            return list(self) == list(other)
        return NotImplemented

    def __repr__(self) -> str:
        return f"HeadBuffers({len(self)} heads)"


class _HeadBufferVec:
    """``Vec<HeadBuffer>`` read in one tight loop into :class:`HeadBuffers`."""

    def read(self, r: Reader) -> HeadBuffers:
        n = r.length()
        buf = r.buf
        pos = r.pos
        ids = array("Q", bytes(8 * n))
        idx = array(_U32_CODE, bytes(4 * n))
        start = pos
        try:
            for i in range(n):
                for k in (0, 1):
                    b = buf[pos]
                    if b < 251:
                        v = b
                        pos += 1
                    elif b == 251:
                        v = buf[pos + 1] | (buf[pos + 2] << 8)
                        pos += 3
                    elif b == 252:
                        v = int.from_bytes(buf[pos + 1 : pos + 5], "little")
                        pos += 5
                    elif b == 253:
                        v = int.from_bytes(buf[pos + 1 : pos + 9], "little")
                        pos += 9
                    else:
                        raise DecodeError(f"varint marker 0x{b:02x} in heads", pos)
                    if k == 0:
                        ids[i] = v
                    else:
                        idx[i] = v  # OverflowError past u32
        except IndexError:
            raise DecodeError(f"heads end early (after {pos - start} bytes)", pos) from None
        except OverflowError:
            raise DecodeError("a head's buffer index does not fit a u32", pos) from None
        if pos > len(buf):
            raise DecodeError(f"heads end early (after {len(buf) - start} bytes)", len(buf))
        r.pos = pos
        hb = HeadBuffers.__new__(HeadBuffers)
        hb.head_ids = ids
        hb.buffer_indices = idx
        return hb

    def write(self, w: Writer, heads: Sequence[HeadBuffer]) -> None:
        if isinstance(heads, HeadBuffers):
            w.varint(len(heads))
            for h, b in zip(heads.head_ids, heads.buffer_indices):
                w.varint(h)
                w.u32(b)
        else:
            Vec(Msg(HeadBuffer)).write(w, heads)


@wire(("queue_us", U64), ("compute_us", U64), ("total_us", U64), ("gpu_us", Opt(U64)))
@dataclass
class FrameTimings:
    """Where the time of a crowd frame went, in microseconds."""

    queue_us: int
    compute_us: int
    total_us: int
    gpu_us: Optional[int]


@wire(
    ("format", FORMAT),
    ("normals", BOOL),
    ("buffers", Vec(Msg(FrameBuffer))),
    ("heads", _HeadBufferVec()),
    ("timings", Msg(FrameTimings)),
)
@dataclass
class CrowdFrameResponse:
    """``POST /v1/crowd/frame`` response: unique buffers, and per head which one it uses."""

    format: str
    normals: bool
    buffers: List[FrameBuffer]
    heads: HeadBuffers
    timings: FrameTimings


# ---------------------------------------------------------------------------------------------
# Rigs, clips, level of detail.


@wire(("host_bytes", U64), ("device_bytes", U64))
@dataclass
class Memory:
    """Memory a rig holds on the server."""

    host_bytes: int
    device_bytes: int


@wire(("min", F32X3), ("max", F32X3))
@dataclass
class Aabb:
    """Axis-aligned box."""

    min: List[float]
    max: List[float]


@wire(("name", STR), ("frames", U32), ("fps", F32))
@dataclass
class ClipInfo:
    """A clip of a rig."""

    name: str
    frames: int
    fps: float


@wire(("name", STR), ("vertices", U32), ("triangles", U32))
@dataclass
class PrimitiveInfo:
    """A primitive of a rig (``mesh/index`` as found in the file)."""

    name: str
    vertices: int
    triangles: int


@wire(("name", STR), ("channels", U32))
@dataclass
class SplitTarget:
    """A target name with more than one weight channel (glTF nodes animated differently)."""

    name: str
    channels: int


@wire(
    ("nodes", U32),
    ("bones", U32),
    ("skinned_vertices", U32),
    ("rigid_vertices", U32),
    ("animated_nodes", Vec(STR)),
    ("clips_with_joints", Vec(STR)),
)
@dataclass
class SkeletonInfo:
    """A skinned rig's skeleton: its vertices follow these bones after the morph targets."""

    nodes: int
    bones: int
    skinned_vertices: int
    rigid_vertices: int
    animated_nodes: List[str]
    clips_with_joints: List[str]


@wire(("shapes", U32), ("mesh", Opt(U32)), ("vertices", U32), ("triangles", U32))
@dataclass
class LodLevelInfo:
    """One LOD level: shapes evaluated, simplified mesh (``None`` = full) and its size."""

    shapes: int
    mesh: Optional[int]
    vertices: int
    triangles: int


@wire(
    ("method", STR),
    ("status", STR),
    ("progress", F32),
    ("error", Opt(STR)),
    ("order", Vec(STR)),
    ("pinned", Vec(STR)),
    ("levels", Vec(Msg(LodLevelInfo))),
)
@dataclass
class LodInfo:
    """A rig's level of detail (``GET /v1/rigs/{id}/lod``)."""

    method: str
    status: str
    progress: float
    error: Optional[str]
    order: List[str]
    pinned: List[str]
    levels: List[LodLevelInfo]


@wire(
    ("id", STR),
    ("name", STR),
    ("builtin", BOOL),
    ("vertices", U32),
    ("triangles", U32),
    ("primitives", Vec(Msg(PrimitiveInfo))),
    ("targets", Vec(STR)),
    ("clips", Vec(Msg(ClipInfo))),
    ("lod", Msg(LodInfo)),
    ("bbox", Msg(Aabb)),
    ("memory", Msg(Memory)),
    ("split_targets", Vec(Msg(SplitTarget))),
    ("graphs", Vec(STR)),
    ("skeleton", Opt(Msg(SkeletonInfo))),
    ("import_notes", Vec(STR)),
)
@dataclass
class RigInfo:
    """A registered rig."""

    id: str
    name: str
    builtin: bool
    vertices: int
    triangles: int
    primitives: List[PrimitiveInfo]
    targets: List[str]
    clips: List[ClipInfo]
    lod: LodInfo
    bbox: Aabb
    memory: Memory
    split_targets: List[SplitTarget] = field(default_factory=list)
    graphs: List[str] = field(default_factory=list)
    skeleton: Optional[SkeletonInfo] = None
    import_notes: List[str] = field(default_factory=list)


@wire(("rigs", Vec(Msg(RigInfo))))
@dataclass
class RigList:
    """``GET /v1/rigs`` response, ordered by id."""

    rigs: List[RigInfo]


@wire(("shapes", U32), ("mesh", Opt(U32)))
@dataclass
class LodLevelRequest:
    """One level of a :class:`LodRequest` table (``mesh`` indexes ``mesh_fractions``)."""

    shapes: int
    mesh: Optional[int] = None


@wire(
    ("method", Opt(STR)),
    ("order", Opt(Vec(STR))),
    ("pinned", Vec(STR)),
    ("levels", Opt(Vec(Msg(LodLevelRequest)))),
    ("mesh_fractions", Vec(F32)),
)
@dataclass
class LodRequest:
    """``PUT /v1/rigs/{id}/lod`` request; every field optional."""

    method: Optional[str] = None
    order: Optional[List[str]] = None
    pinned: List[str] = field(default_factory=list)
    levels: Optional[List[LodLevelRequest]] = None
    mesh_fractions: List[float] = field(default_factory=list)


@wire(
    ("name", STR),
    ("first_vertex", U32),
    ("vertices", U32),
    ("first_index", U32),
    ("indices", U32),
    ("material", Opt(U32)),
)
@dataclass
class MeshPrimitive:
    """A primitive's vertex and index ranges in a :class:`MeshResponse`, and its material
    (an index into ``Client.materials(rig)["materials"]``, or None)."""

    name: str
    first_vertex: int
    vertices: int
    first_index: int
    indices: int
    material: Optional[int] = None


@wire(
    ("rig", STR),
    ("lod", U32),
    ("vertices", U32),
    ("primitives", Vec(Msg(MeshPrimitive))),
    ("bbox", Msg(Aabb)),
    ("quantization", Msg(Quantization)),
    ("indices", BLOB),
    ("positions", BLOB),
    ("normals", BLOB),
    ("uvs", BLOB),
    ("uvs1", BLOB),
    ("colors", BLOB),
)
@dataclass
class MeshResponse:
    """``GET /v1/rigs/{id}/mesh`` response (payloads still encoded)."""

    rig: str
    lod: int
    vertices: int
    primitives: List[MeshPrimitive]
    bbox: Aabb
    quantization: Quantization
    indices: Any
    positions: Any
    normals: Any
    uvs: Any = b""
    uvs1: Any = b""
    colors: Any = b""


@wire(("rig", STR), ("added", Vec(Msg(ClipInfo))), ("ignored", Vec(STR)))
@dataclass
class ClipUpload:
    """``POST /v1/rigs/{id}/clips`` response."""

    rig: str
    added: List[ClipInfo]
    ignored: List[str]


@wire(("rig", STR), ("clips", Vec(Msg(ClipInfo))))
@dataclass
class ClipList:
    """``GET /v1/rigs/{id}/clips`` response."""

    rig: str
    clips: List[ClipInfo]


@wire(("column", STR), ("node", STR), ("axis", F32X3), ("scale", F32))
@dataclass
class JointChannelSpec:
    """One clip column that turns a skeleton node: a value ``v`` turns ``node`` by
    ``v * scale`` radians about ``axis``, an axis of rig space (+Y up, +Z out of the face, +X
    to the character's left; normalized by the server), about the node's origin. ``column``
    matches clip columns loosely, as target names do."""

    column: str
    node: str
    axis: List[float] = field(default_factory=lambda: [0.0, 1.0, 0.0])
    scale: float = 1.0


@wire(("channels", Vec(Msg(JointChannelSpec))))
@dataclass
class JointMapSpec:
    """``PUT /v1/rigs/{id}/joint-map`` request: the columns that turn the rig's joints, in the
    order their rotations compose per node (at most 256, each column once)."""

    channels: List[JointChannelSpec] = field(default_factory=list)


@wire(("rig", STR), ("default", BOOL), ("channels", Vec(Msg(JointChannelSpec))))
@dataclass
class JointMapInfo:
    """A rig's joint map in force (``GET``, ``PUT`` and ``DELETE /v1/rigs/{id}/joint-map``):
    ``default`` is true when the rig has no map of its own and ``channels`` are the defaults
    (Live Link Face's head and eye angles onto ``Head``/``head``/``J_Bip_C_Head`` and the eye
    joints, whichever the skeleton has; none for a rig without a skeleton)."""

    rig: str
    default: bool
    channels: List[JointChannelSpec] = field(default_factory=list)


@dataclass
class Readiness:
    """``GET /readyz`` body (always JSON)."""

    status: str
    backend: str
    cpu_isa: str
    degraded_reason: Optional[str]
    rigs: int
    skipped_files: List[str]
    renderer: Optional[str] = None

    @classmethod
    def from_json(cls, obj: dict) -> "Readiness":
        # A missing "renderer" (an older server) reads as None, as the protocol says.
        return cls(
            status=obj["status"],
            backend=obj["backend"],
            cpu_isa=obj["cpu_isa"],
            degraded_reason=obj.get("degraded_reason"),
            rigs=obj["rigs"],
            skipped_files=list(obj.get("skipped_files", [])),
            renderer=obj.get("renderer"),
        )


# ---------------------------------------------------------------------------------------------
# Rendered frames.


@wire(("head", U64), ("position", F32X3), ("yaw", F32), ("scale", F32))
@dataclass
class Placement:
    """Where every head with id ``head`` stands: translate · rotate_y(yaw°) · scale."""

    head: int
    position: List[float]
    yaw: float = 0.0
    scale: float = 1.0


class _CameraPoint:
    """A camera's ``position`` or ``target``: bincode's ``[f32; 3]``, always there. A framing
    camera (``frame``) has neither and is JSON-only: writing it as bincode is an error."""

    def read(self, r: Reader) -> List[float]:
        return F32X3.read(r)

    def write(self, w: Writer, v: Optional[Sequence[float]]) -> None:
        if v is None:
            raise ValueError(
                "a camera without position and target (a framing camera) has no bincode form; "
                "it is sent as JSON"
            )
        F32X3.write(w, v)


class _JsonOnly:
    """A field only JSON carries (its bincode layout is pinned): no bytes in bincode, ``None``
    when read; :func:`as_dict` leaves it out while it is ``None``."""

    def read(self, r: Reader) -> None:
        return None

    def write(self, w: Writer, v: Any) -> None:
        pass


_CAMERA_POINT = _CameraPoint()
#: Framing presets of :class:`CameraSpec`.
CAMERA_FRAMES = ("faces", "bodies")


@wire(
    ("position", _CAMERA_POINT),
    ("target", _CAMERA_POINT),
    ("fov_y", F32),
    ("near", Opt(F32)),
    ("far", Opt(F32)),
    ("frame", _JsonOnly()),
)
@dataclass
class CameraSpec:
    """A perspective camera; +Y is up. Either ``position`` and ``target``, or ``frame``:
    ``"faces"`` (the front view fitted to every head's face) or ``"bodies"`` (fitted to the
    whole figures, as without a camera). A framing camera is JSON-only: ``Client.render``
    sends a request with one as JSON."""

    position: Optional[List[float]] = None
    target: Optional[List[float]] = None
    fov_y: float = 30.0
    near: Optional[float] = None
    far: Optional[float] = None
    frame: Optional[str] = field(default=None, metadata={"json_only": True})


@wire(
    ("width", U32),
    ("height", U32),
    ("format", IMAGE_FORMAT),
    ("quality", U8),
    ("background", U8X3),
)
@dataclass
class ImageOptions:
    """Size, encoding (``png``, ``jpeg``, ``rgba``) and background of a rendered image."""

    width: int = 640
    height: int = 480
    format: str = "png"
    quality: int = 90
    background: List[int] = field(default_factory=lambda: [46, 50, 56])


@wire(
    ("heads", HEADS),
    ("wrap", BOOL),
    ("placements", Opt(Vec(Msg(Placement)))),
    ("camera", Opt(Msg(CameraSpec))),
    ("image", Opt(Msg(ImageOptions))),
)
@dataclass
class RenderRequest:
    """``POST /v1/crowd/render`` request; the response is the image itself."""

    heads: List[Head]
    wrap: bool = True
    placements: Optional[List[Placement]] = None
    camera: Optional[CameraSpec] = None
    image: Optional[ImageOptions] = None


# ---------------------------------------------------------------------------------------------
# Crowd sessions.

#: ``HeadBuffer.buffer`` of a stream head whose job is the one in the last message this viewer
#: received: keep drawing what it had (``u32::MAX``).
HEAD_UNCHANGED = 0xFFFF_FFFF
#: ``HeadBuffer.buffer`` of a stream head with nothing to draw: its rig or clip was deleted.
HEAD_MISSING = 0xFFFF_FFFE


@wire(("name", STR), ("start", STR), ("seed", U64), ("script", Vec(STR)))
@dataclass
class GraphPlay:
    """How a session head plays a motion graph: from node ``start``, through ``script`` (node
    names) or, without one, on a random walk seeded by ``seed``."""

    name: str
    start: str
    seed: int = 0
    script: List[str] = field(default_factory=list)


@wire(("min_cutoff", F32), ("beta", F32), ("d_cutoff", F32))
@dataclass
class OneEuro:
    """The One Euro filter of a live head without timecodes: cutoff at rest (Hz), how fast
    the cutoff rises with speed, and the speed's own cutoff (Hz)."""

    min_cutoff: float = 1.0
    beta: float = 0.0
    d_cutoff: float = 1.0


@wire(
    ("hold_ms", U32),
    ("fade_ms", U32),
    ("delay_ms", U32),
    ("smoothing", Opt(Msg(OneEuro))),
    ("mapping", Opt(STR)),
)
@dataclass
class LiveSpec:
    """How a session head follows live input (``POST /v1/sessions/{id}/live``): it holds the
    last input ``hold_ms`` once producers go quiet, fades to and from live input over
    ``fade_ms``, plays timecoded input ``delay_ms`` behind the producer, and smooths input
    without timecodes with ``smoothing``; ``mapping`` names a rig mapping for the producer's
    names."""

    hold_ms: int = 500
    fade_ms: int = 250
    delay_ms: int = 100
    smoothing: Optional[OneEuro] = None
    mapping: Optional[str] = None

    def __post_init__(self) -> None:
        if isinstance(self.smoothing, Mapping):
            self.smoothing = OneEuro(**self.smoothing)


def _live_spec(v: Any) -> Optional[LiveSpec]:
    if v is None or isinstance(v, LiveSpec):
        return v
    if isinstance(v, Mapping):
        return LiveSpec(**v)
    raise TypeError(f"live is a LiveSpec or a dict, not {v!r}")


@wire(("head", U64), ("weights", _WEIGHTS), ("joints", JOINTS), ("t", Opt(F64)))
@dataclass
class LiveSample:
    """One producer sample for a live session head: weights by name (through the head's
    mapping) or dense, node rotations in ``joints``, and the producer's timecode ``t`` (s)."""

    head: int
    weights: Any = None
    joints: Dict[str, JointTransform] = field(default_factory=dict)
    t: Optional[float] = None

    def __post_init__(self) -> None:
        j = self.joints
        if type(j) is not dict or j:
            self.joints = joint_overrides(j)


@wire(("heads", Vec(Msg(LiveSample))))
@dataclass
class LiveInput:
    """``POST /v1/sessions/{id}/live`` body, and one message of the live WebSocket."""

    heads: List[LiveSample] = field(default_factory=list)


@wire(("accepted", U32))
@dataclass
class LiveAck:
    """The answer to ``POST /v1/sessions/{id}/live``: samples taken."""

    accepted: int


@wire(
    ("blink", BOOL),
    ("saccades", BOOL),
    ("look_at", Opt(F32X3)),
    ("breathing", BOOL),
    ("seed", Opt(U64)),
)
@dataclass
class Alive:
    """Liveliness without authoring for a session head (or a session's default): blinks
    (about every 4 s), eye saccades, a world point to look at, breathing; ``seed`` absent, one
    derived from the head id, so a crowd never blinks in unison (``proto/README.md``,
    "Liveliness")."""

    blink: bool = False
    saccades: bool = False
    look_at: Optional[List[float]] = None
    breathing: bool = False
    seed: Optional[int] = None


def _alive(a: Any) -> Optional[Alive]:
    """An :class:`Alive`, from itself, a dict with its keys, or None."""
    if a is None or type(a) is Alive:
        return a
    if isinstance(a, Mapping):
        return Alive(**a)
    raise TypeError(f"alive is an Alive or a dict, not {type(a).__name__}")


@wire(
    ("head", U64),
    ("rig", STR),
    ("clip", STR),
    ("offset", I64),
    ("position", F32X3),
    ("yaw", F32),
    ("scale", F32),
    ("graph", Opt(Msg(GraphPlay))),
    ("joints", JOINTS),
    ("layers", _LAYERS),
    ("clamp", CLAMP),
    ("live", Opt(Msg(LiveSpec))),
    ("alive", Opt(Msg(Alive))),
)
@dataclass
class SessionHead:
    """One head of a session: at tick ``t`` it plays frame
    ``offset + floor((t - 1) * clip_fps / session_fps)`` of its clip (or its ``graph``),
    standing at ``position`` turned ``yaw`` degrees about +Y and scaled by ``scale``; on a rig
    with a skeleton, ``joints`` sets named nodes' local transforms over that pose at every tick
    (as :attr:`Head.joints`). ``layers`` go over that pose as :attr:`Head.layers` do, their
    frames counted from the session clock as ``offset`` is; ``clamp`` bounds the final weights.
    A head with ``live`` (a :class:`LiveSpec` or a dict) shows the input producers send for it
    over that pose (over the neutral without a clip).
    An empty ``clip`` without a graph plays the rig's neutral (a rig with no clips); ``alive``
    adds procedural blinks, saccades, look-at and breathing (else the session's ``alive``)."""

    head: int
    rig: str
    clip: str = ""
    offset: int = 0
    position: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    yaw: float = 0.0
    scale: float = 1.0
    graph: Optional[GraphPlay] = None
    joints: Dict[str, JointTransform] = field(default_factory=dict)
    layers: List[Layer] = field(default_factory=list)
    clamp: Optional[Sequence[float]] = None
    live: Optional[LiveSpec] = None
    alive: Optional[Alive] = None

    def __post_init__(self) -> None:
        self.alive = _alive(self.alive)
        j = self.joints
        if type(j) is not dict or j:
            self.joints = joint_overrides(j)
        if self.layers and any(type(x) is not Layer for x in self.layers):
            self.layers = [_of_head_layer(x) for x in self.layers]
        if self.live is not None and type(self.live) is not LiveSpec:
            self.live = _live_spec(self.live)


@wire(
    ("fps", F32),
    ("wrap", BOOL),
    ("idle_timeout_s", U32),
    ("heads", Vec(Msg(SessionHead))),
    ("alive", Opt(Msg(Alive))),
)
@dataclass
class SessionRequest:
    """``POST /v1/sessions`` request: ticks per second (0–120], whether clips loop (else they
    hold their last frame), seconds without viewers before the session ends, the crowd, and
    the liveliness of heads without their own ``alive``."""

    fps: float = 30.0
    wrap: bool = True
    idle_timeout_s: int = 60
    heads: List[SessionHead] = field(default_factory=list)
    alive: Optional[Alive] = None

    def __post_init__(self) -> None:
        self.alive = _alive(self.alive)


@wire(
    ("ticks", U64),
    ("ticks_late", U64),
    ("ticks_skipped", U64),
    ("jobs", U64),
    ("messages_sent", U64),
    ("messages_dropped", U64),
    ("bytes_sent", U64),
)
@dataclass
class SessionStats:
    """A session's counters since it started."""

    ticks: int
    ticks_late: int
    ticks_skipped: int
    jobs: int
    messages_sent: int
    messages_dropped: int
    bytes_sent: int


@wire(
    ("id", STR),
    ("fps", F32),
    ("wrap", BOOL),
    ("idle_timeout_s", U32),
    ("tick", U64),
    ("heads", Vec(Msg(SessionHead))),
    ("viewers", U32),
    ("stats", Msg(SessionStats)),
    ("alive", Opt(Msg(Alive))),
)
@dataclass
class SessionInfo:
    """A session (``GET /v1/sessions/{id}``; also the answer to create and patch): ``tick``
    is the last tick computed (0 before the first), ``heads`` in the order stream messages
    list them."""

    id: str
    fps: float
    wrap: bool
    idle_timeout_s: int
    tick: int
    heads: List[SessionHead]
    viewers: int
    stats: SessionStats
    alive: Optional[Alive] = None


@wire(("sessions", Vec(Msg(SessionInfo))))
@dataclass
class SessionList:
    """``GET /v1/sessions`` response, ordered by id."""

    sessions: List[SessionInfo]


@wire(
    ("head", U64),
    ("clip", Opt(STR)),
    ("offset", Opt(I64)),
    ("position", Opt(F32X3)),
    ("yaw", Opt(F32)),
    ("scale", Opt(F32)),
    ("node", Opt(STR)),
    ("joints", Opt(JOINTS)),
    ("layers", Opt(_LAYERS)),
    ("clamp", CLAMP),
    ("live", Opt(Msg(LiveSpec))),
    ("alive", Opt(Msg(Alive))),
)
@dataclass
class HeadChange:
    """A change to one session head; ``None`` fields stay as they are. ``joints`` replaces the
    head's joint overrides (``{}`` clears them), ``layers`` its layers (``[]`` clears them)."""

    head: int
    clip: Optional[str] = None
    offset: Optional[int] = None
    position: Optional[List[float]] = None
    yaw: Optional[float] = None
    scale: Optional[float] = None
    node: Optional[str] = None
    joints: Optional[Dict[str, JointTransform]] = None
    layers: Optional[List[Layer]] = None
    clamp: Optional[Sequence[float]] = None
    live: Optional[LiveSpec] = None
    alive: Optional[Alive] = None

    def __post_init__(self) -> None:
        self.alive = _alive(self.alive)
        j = self.joints
        if j is not None and (type(j) is not dict or j):
            self.joints = joint_overrides(j)
        if self.layers and any(type(x) is not Layer for x in self.layers):
            self.layers = [_of_head_layer(x) for x in self.layers]
        if self.live is not None and type(self.live) is not LiveSpec:
            self.live = _live_spec(self.live)


class _U32Pair:
    """``[u32; 2]``: two varints, no length (a fixed-size array)."""

    def read(self, r: Reader) -> List[int]:
        return [r.u32(), r.u32()]

    def write(self, w: Writer, v: Sequence[int]) -> None:
        a, b = v
        w.u32(operator.index(a))
        w.u32(operator.index(b))


U32X2 = _U32Pair()


@wire(("name", STR), ("clip", STR), ("frames", Opt(U32X2)))
@dataclass
class GraphNode:
    """A motion-graph node: a clip, or its frames ``[first, last]``."""

    name: str
    clip: str
    frames: Optional[List[int]] = None


@wire(("from_", STR), ("to", STR), ("fade", U32), ("window", Opt(U32X2)))
@dataclass
class GraphEdge:
    """A transition: ``to`` fades in over ``fade`` frames, starting within ``window``."""

    from_: str
    to: str
    fade: int
    window: Optional[List[int]] = None


MAP_OVERRIDE = Enum("none", "block", "blend")


@wire(
    ("source", STR),
    ("target", STR),
    ("gain", F32),
    ("offset", F32),
    ("clamp", CLAMP),
)
@dataclass
class MapEntry:
    """One entry of a :class:`Mapping`: ``target += gain · source + offset``, the target's
    sum then clamped into every ``clamp`` its entries give."""

    source: str
    target: str
    gain: float = 1.0
    offset: float = 0.0
    clamp: Optional[Sequence[float]] = None


@wire(
    ("name", STR),
    ("binary", BOOL),
    ("override_blink", MAP_OVERRIDE),
    ("override_look_at", MAP_OVERRIDE),
    ("override_mouth", MAP_OVERRIDE),
)
@dataclass
class MapSource:
    """A source that is binary (VRM's ``isBinary``) or overrides VRM 1.0's blink, look-at or
    mouth expressions (``"none"``, ``"block"``, ``"blend"``)."""

    name: str
    binary: bool = False
    override_blink: str = "none"
    override_look_at: str = "none"
    override_mouth: str = "none"


@wire(("entries", Vec(Msg(MapEntry))), ("sources", Vec(Msg(MapSource))))
@dataclass
class MappingSpec:
    """A rig's mapping from a producer's names to its targets
    (``PUT /v1/rigs/{id}/mappings/{name}``; ``proto/README.md``, "Mappings"; the Rust type
    ``Mapping``, renamed here beside ``typing.Mapping``)."""

    entries: List[MapEntry] = field(default_factory=list)
    sources: List[MapSource] = field(default_factory=list)


@wire(("nodes", Vec(Msg(GraphNode))), ("edges", Vec(Msg(GraphEdge))))
@dataclass
class MotionGraph:
    """A rig's motion graph (``PUT /v1/rigs/{id}/graphs/{name}``)."""

    nodes: List[GraphNode] = field(default_factory=list)
    edges: List[GraphEdge] = field(default_factory=list)


@wire(("rig", STR), ("name", STR), ("graph", Msg(MotionGraph)))
@dataclass
class GraphInfo:
    """A stored motion graph."""

    rig: str
    name: str
    graph: MotionGraph


@wire(
    ("info", Msg(GraphInfo)),
    ("costs", Vec(F32)),
    ("candidates", U32),
    ("dropped_nodes", U32),
)
@dataclass
class BuiltGraph:
    """A graph built from a rig's clips (``POST /v1/rigs/{id}/graphs/{name}?auto=1``), with
    each edge's cost as a fraction of the rig's diagonal."""

    info: GraphInfo
    costs: List[float] = field(default_factory=list)
    candidates: int = 0
    dropped_nodes: int = 0


@wire(("graphs", Vec(Msg(GraphInfo))))
@dataclass
class GraphList:
    """A rig's motion graphs."""

    graphs: List[GraphInfo] = field(default_factory=list)


@wire(
    ("remove", Vec(U64)),
    ("change", Vec(Msg(HeadChange))),
    ("add", Vec(Msg(SessionHead))),
    ("alive", Opt(Msg(Alive))),
)
@dataclass
class SessionPatch:
    """``PATCH /v1/sessions/{id}`` request, applied at the next tick: remove, change, add;
    ``alive`` replaces the session's liveliness (e.g. a look-at point moved every tick)."""

    remove: List[int] = field(default_factory=list)
    change: List[HeadChange] = field(default_factory=list)
    add: List[SessionHead] = field(default_factory=list)
    alive: Optional[Alive] = None

    def __post_init__(self) -> None:
        self.alive = _alive(self.alive)


@wire(
    ("tick", U64),
    ("format", FORMAT),
    ("normals", BOOL),
    ("layout", Opt(Vec(Msg(SessionHead)))),
    ("buffers", Vec(Msg(FrameBuffer))),
    ("heads", _HeadBufferVec()),
    ("timings", Msg(FrameTimings)),
)
@dataclass
class TickVertices:
    """Stream message variant 0: a tick's vertex buffers for one viewer (payloads encoded).

    ``layout`` is the session's heads when they changed since the viewer's last message (always
    in its first); ``heads`` has one entry per layout head, in layout order, whose ``buffer`` is
    an index into ``buffers``, :data:`HEAD_UNCHANGED` or :data:`HEAD_MISSING`."""

    tick: int
    format: str
    normals: bool
    layout: Optional[List[SessionHead]]
    buffers: List[FrameBuffer]
    heads: HeadBuffers
    timings: FrameTimings


@wire(("tick", U64), ("format", IMAGE_FORMAT), ("width", U32), ("height", U32), ("image", BLOB))
@dataclass
class TickFrame:
    """Stream message variant 1: a tick drawn from the viewer's camera (``png``, ``jpeg`` or
    ``rgba`` bytes in ``image``)."""

    tick: int
    format: str
    width: int
    height: int
    image: Any


@wire(
    ("tick", U64),
    ("format", FORMAT),
    ("normals", BOOL),
    ("layout", Opt(Vec(Msg(SessionHead)))),
    ("residual", Vec(BOOL)),
    ("buffers", Vec(Msg(FrameBuffer))),
    ("heads", _HeadBufferVec()),
    ("timings", Msg(FrameTimings)),
)
@dataclass
class TickDelta:
    """Stream message variant 2 (a viewer that asked for ``temporal``): :class:`TickVertices`
    with one ``residual`` flag per buffer. A buffer whose flag is false is a keyframe, plain
    q16; one whose flag is true holds, for each head that names it, that head's q16 values as
    ``q16r`` byte planes against the buffer this viewer last received for the same head id
    (normals likewise). ``format`` is what the buffers decode to (always ``q16``)."""

    tick: int
    format: str
    normals: bool
    layout: Optional[List[SessionHead]]
    residual: List[bool]
    buffers: List[FrameBuffer]
    heads: HeadBuffers
    timings: FrameTimings


#: Most bytes a packed message may claim once decompressed (as the Rust reader: 1 GiB).
MAX_UNPACKED_BYTES = 1 << 30


@wire(("encoding", MESSAGE_ENCODING), ("length", U64), ("data", BLOB))
@dataclass
class PackedMessage:
    """Stream message variant 3 (a viewer that asked for ``compression``): ``data``
    decompresses (``encoding``: ``zstd`` or ``deflate``, a zlib stream) to ``length`` bytes,
    the bincode of one whole stream message that is not itself packed."""

    encoding: str
    length: int
    data: Any

    def unpack(self, limit: int = MAX_UNPACKED_BYTES) -> bytes:
        """The decompressed bytes. A ``length`` over ``limit``, data that decompresses to more
        or fewer bytes than ``length`` (found without inflating past it) or is not valid
        compressed data is a :class:`~crowdmorph.wire.DecodeError`; zstd needs the optional
        ``zstandard`` package (:class:`ImportError` without it)."""
        n = self.length
        if n > limit:
            raise DecodeError(f"a packed message claims {n} bytes, more than {limit}")
        if self.encoding == "deflate":
            out = _inflate_zlib(self.data, n)
        elif self.encoding == "zstd":
            out = _inflate_zstd(self.data, n)
        else:  # pragma: no cover - the enum has no other names
            raise DecodeError(f"unknown packed encoding {self.encoding!r}")
        if len(out) != n:
            got = "more" if len(out) > n else str(len(out))
            raise DecodeError(f"a packed message of {got} bytes claimed {n}")
        return out


def _inflate_zlib(data: Any, n: int) -> bytes:
    import zlib

    d = zlib.decompressobj()
    try:
        # At most one byte past the claim: enough to tell "more" without inflating it all.
        out = d.decompress(data, n + 1)
    except zlib.error as e:
        raise DecodeError(f"bad deflate data: {e}") from None
    if len(out) <= n and not d.eof:
        raise DecodeError("bad deflate data: the zlib stream ends early")
    return out


#: What to install when zstd messages are asked for without the ``zstandard`` package.
ZSTD_HINT = "pip install 'crowdmorph[zstd]' (or pip install zstandard)"


def _zstandard() -> Any:
    try:
        import zstandard  # type: ignore[import-not-found]
    except ImportError as e:
        raise ImportError(
            f"zstd compression needs the zstandard package: {ZSTD_HINT}", name="zstandard"
        ) from e
    return zstandard


def _inflate_zstd(data: Any, n: int) -> bytes:
    import io

    zstandard = _zstandard()
    try:
        reader = zstandard.ZstdDecompressor().stream_reader(
            io.BytesIO(data), read_across_frames=True
        )
        parts = []
        got = 0
        while got <= n:
            chunk = reader.read(n + 1 - got)
            if not chunk:
                break
            parts.append(chunk)
            got += len(chunk)
    except zstandard.ZstdError as e:
        raise DecodeError(f"bad zstd data: {e}") from None
    return b"".join(parts)


@wire(("head", U64), ("inputs", Vec(F32)))
@dataclass
class HeadLayers:
    """One head's expression-layer inputs, in the order ``GET /v1/rigs/{id}/layers`` numbers
    them."""

    head: int
    inputs: List[float]


@wire(("tick", U64), ("heads", Vec(Msg(HeadLayers))))
@dataclass
class TickLayers:
    """Stream message variant 4, only for a viewer whose hello asked for ``layers`` (this
    client never does): the heads whose expression-layer inputs changed."""

    tick: int
    heads: List[HeadLayers]


# ---------------------------------------------------------------------------------------------
# Poses for clients that blend themselves (``"format": "weights"``, ``"output": "weights"``).


@wire(
    ("node", U32),
    ("rotation", F32X4),
    ("translation", Opt(F32X3)),
    ("scale", Opt(F32X3)),
)
@dataclass
class NodePose:
    """A skeleton node's local transform in a pose, where it differs from rest: ``node``
    indexes :attr:`RigChannels.nodes`; ``rotation`` (x, y, z, w) is always given,
    ``translation`` and ``scale`` only where they differ from the node's rest values."""

    node: int
    rotation: List[float]
    translation: Optional[List[float]] = None
    scale: Optional[List[float]] = None


@wire(("weights", BLOB), ("joints", Vec(Msg(NodePose))))
@dataclass
class HeadPose:
    """One head's final pose: ``weights``, one IEEE binary16 per weight channel
    (little-endian, in :attr:`RigChannels.targets` order; :meth:`weights_f32` reads them), and
    ``joints``, every skeleton node not at rest (nodes not listed are at rest)."""

    weights: Any
    joints: List[NodePose] = field(default_factory=list)

    def weights_f32(self) -> List[float]:
        """The weights as Python floats (binary16 values, exactly)."""
        raw = bytes(self.weights)
        if len(raw) % 2:
            raise DecodeError(f"{len(raw)} bytes of binary16 weights")
        return list(struct.unpack(f"<{len(raw) // 2}e", raw))


@wire(
    ("format", FORMAT),
    ("poses", Vec(Msg(HeadPose))),
    ("heads", _HeadBufferVec()),
    ("timings", Msg(FrameTimings)),
)
@dataclass
class CrowdPoseResponse:
    """``POST /v1/crowd/frame`` response to ``"format": "weights"``: unique poses (clones share
    one) and per request head the index of its pose; ``format`` is always ``"weights"``."""

    format: str
    poses: List[HeadPose]
    heads: HeadBuffers
    timings: FrameTimings


@wire(("rig", STR), ("targets", Vec(STR)), ("nodes", Vec(STR)))
@dataclass
class RigChannels:
    """``GET /v1/rigs/{id}/channels``: the rig's weight channels (``name``, or ``name#k`` for
    a name with several) and its skeleton's nodes, in the order poses number them."""

    rig: str
    targets: List[str]
    nodes: List[str]


@wire(
    ("tick", U64),
    ("layout", Opt(Vec(Msg(SessionHead)))),
    ("poses", Vec(Msg(HeadPose))),
    ("heads", _HeadBufferVec()),
    ("timings", Msg(FrameTimings)),
)
@dataclass
class TickPoses:
    """Stream message variant 5, for a viewer whose hello asked for ``"output": "weights"``:
    the poses of the heads whose pose changed since the viewer's last message; ``heads`` has
    one entry per layout head (an index into ``poses``, :data:`HEAD_UNCHANGED` or
    :data:`HEAD_MISSING`)."""

    tick: int
    layout: Optional[List[SessionHead]]
    poses: List[HeadPose]
    heads: HeadBuffers
    timings: FrameTimings


#: ``StreamMessage``: the binary messages of a session stream, by variant index.
STREAM_MESSAGE = Tagged(TickVertices, TickFrame, TickDelta, PackedMessage, TickLayers, TickPoses)

StreamMessage = Union[TickVertices, TickFrame, TickDelta, PackedMessage, TickLayers, TickPoses]


def decode_stream_message(data: Any) -> StreamMessage:
    """One binary message of a session stream: a :class:`TickVertices`, :class:`TickFrame`,
    :class:`TickDelta` or :class:`PackedMessage` (payloads are slices of ``data``)."""
    return decode_as(STREAM_MESSAGE, data)


def unpack_stream_message(data: Any) -> Union[TickVertices, TickFrame, TickDelta]:
    """One binary message of a session stream, decompressed when it is a
    :class:`PackedMessage` (whose payload must be a message of another variant)."""
    m = decode_stream_message(data)
    if not isinstance(m, PackedMessage):
        return m
    inner = decode_as(STREAM_MESSAGE, m.unpack())
    if isinstance(inner, PackedMessage):
        raise DecodeError("a packed message inside a packed message")
    return inner


def as_dict(message: Any) -> Any:
    """The protocol's JSON form of a message: field names as keys, ``Blob`` payloads as
    base64 strings, ``None`` as ``null``, joint overrides as an object by node name. Handy for
    printing and for comparing with the server's JSON."""
    if dataclasses.is_dataclass(message) and not isinstance(message, type):
        # A field named after a Python keyword has a trailing underscore (``GraphEdge.from_``).
        # A JSON-only field is absent while None, as the server writes it.
        return {
            f.name.rstrip("_"): as_dict(getattr(message, f.name))
            for f in dataclasses.fields(message)
            if not (f.metadata.get("json_only") and getattr(message, f.name) is None)
        }
    if isinstance(message, Mapping):
        # Live weights, joint overrides: objects by name.
        return {k: as_dict(v) for k, v in message.items()}
    if isinstance(message, (list, tuple, HeadBuffers)):
        return [as_dict(v) for v in message]
    if isinstance(message, (memoryview, bytes, bytearray)):
        return base64.b64encode(message).decode("ascii")
    return message

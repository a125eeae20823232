"""Python client of the crowdmorph blendshape crowd server (v1 protocol).

Speaks the binary protocol (``application/x-bincode``) of ``proto/README.md``; standard library
only, numpy optional (decoded vertex arrays are numpy arrays when it is installed), and
``websockets`` (11 or later) for session streams only (``pip install 'crowdmorph[sessions]'``)::

    import crowdmorph

    with crowdmorph.Client("http://127.0.0.1:8080") as c:
        frame = c.crowd_frame([(7, "default-head", "talk", 12)], format="q16")
        xyz = frame.positions(0)          # (vertices, 3) float32, dequantized

Modules: :mod:`~crowdmorph.client` (the HTTP client), :mod:`~crowdmorph.results` (decoded
results: buffers, crowd frames, meshes, images), :mod:`~crowdmorph.sessions` (session
viewers, over the ``websockets`` client), :mod:`~crowdmorph.messages` (the wire messages),
:mod:`~crowdmorph.wire` (bincode), :mod:`~crowdmorph.arrays` (payload decoding),
:mod:`~crowdmorph.errors` (typed errors) and :mod:`~crowdmorph.obj` (OBJ output).
"""

from .arrays import HAVE_NUMPY
from .client import BINCODE, Client, Response, self_contained_gltf
from .errors import (
    BadRequest,
    Conflict,
    CrowdmorphError,
    DeadlineExceeded,
    Forbidden,
    NotFound,
    Overloaded,
    ProtocolError,
    ServerError,
    StreamClosed,
    TooLarge,
    Unauthorized,
    Unavailable,
    UnsupportedMediaType,
    Unprocessable,
)
from .messages import (
    Aabb,
    BlendLayer,
    CameraSpec,
    ClipInfo,
    ClipList,
    ClipUpload,
    CrowdFrameRequest,
    CrowdFrameResponse,
    FrameBuffer,
    FrameTimings,
    Head,
    HeadBuffer,
    HeadBuffers,
    ImageOptions,
    LodInfo,
    LodLevelInfo,
    LodLevelRequest,
    LodRequest,
    Memory,
    MeshPrimitive,
    MeshResponse,
    OutputOptions,
    Placement,
    PrimitiveInfo,
    SplitTarget,
    Quantization,
    Readiness,
    RenderRequest,
    RigInfo,
    RigList,
    HEAD_MISSING,
    HEAD_UNCHANGED,
    HeadChange,
    SessionHead,
    SessionInfo,
    SessionList,
    SessionPatch,
    SessionRequest,
    SessionStats,
    TickFrame,
    TickVertices,
    as_dict,
    decode_stream_message,
)
from .obj import write_obj
from .results import Buffer, CrowdFrame, Image, Mesh
from .sessions import StreamFrame, Tick, Viewer
from .wire import DecodeError, decode, encode

#: The wire protocol version this client speaks (the ``/v1`` of every path).
PROTOCOL_VERSION = 1

__version__ = "0.1.0"

__all__ = [
    "PROTOCOL_VERSION",
    "HAVE_NUMPY",
    "BINCODE",
    "Client",
    "CrowdFrame",
    "Buffer",
    "Mesh",
    "Image",
    "Response",
    "self_contained_gltf",
    "write_obj",
    "CrowdmorphError",
    "BadRequest",
    "Unauthorized",
    "Forbidden",
    "NotFound",
    "Conflict",
    "TooLarge",
    "UnsupportedMediaType",
    "Unprocessable",
    "ServerError",
    "Unavailable",
    "Overloaded",
    "DeadlineExceeded",
    "ProtocolError",
    "StreamClosed",
    "Viewer",
    "Tick",
    "StreamFrame",
    "Head",
    "BlendLayer",
    "OutputOptions",
    "CrowdFrameRequest",
    "CrowdFrameResponse",
    "FrameBuffer",
    "HeadBuffer",
    "HeadBuffers",
    "FrameTimings",
    "Quantization",
    "Memory",
    "Aabb",
    "ClipInfo",
    "PrimitiveInfo",
    "SplitTarget",
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
    "Readiness",
    "Placement",
    "CameraSpec",
    "ImageOptions",
    "RenderRequest",
    "SessionHead",
    "SessionRequest",
    "SessionStats",
    "SessionInfo",
    "SessionList",
    "HeadChange",
    "SessionPatch",
    "TickVertices",
    "TickFrame",
    "HEAD_UNCHANGED",
    "HEAD_MISSING",
    "decode_stream_message",
    "as_dict",
    "encode",
    "decode",
    "DecodeError",
]

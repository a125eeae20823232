"""Python client of the crowdmorph blendshape crowd server (v1 protocol).

Speaks the binary protocol (``application/x-bincode``) of ``proto/README.md``; standard library
only, numpy optional (decoded vertex arrays are numpy arrays when it is installed)::

    import crowdmorph

    with crowdmorph.Client("http://127.0.0.1:8080") as c:
        frame = c.crowd_frame([(7, "default-head", "talk", 12)], format="q16")
        xyz = frame.positions(0)          # (vertices, 3) float32, dequantized

Modules: :mod:`~crowdmorph.client` (the HTTP client and decoded results),
:mod:`~crowdmorph.messages` (the wire messages), :mod:`~crowdmorph.wire` (bincode),
:mod:`~crowdmorph.arrays` (payload decoding), :mod:`~crowdmorph.errors` (typed errors),
:mod:`~crowdmorph.obj` (OBJ output).
"""

from .arrays import HAVE_NUMPY
from .client import (
    BINCODE,
    Buffer,
    Client,
    CrowdFrame,
    Image,
    Mesh,
    Response,
    self_contained_gltf,
)
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
    TooLarge,
    Unauthorized,
    Unavailable,
    UnsupportedMediaType,
    Unprocessable,
)
from .messages import (
    Aabb,
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
    Quantization,
    Readiness,
    RenderRequest,
    RigInfo,
    RigList,
    as_dict,
)
from .obj import write_obj
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
    "Head",
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
    "as_dict",
    "encode",
    "decode",
    "DecodeError",
]

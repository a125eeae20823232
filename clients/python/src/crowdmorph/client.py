"""The HTTP client: one kept-alive connection, bincode bodies, typed errors.

:class:`Client` has one method per endpoint of ``proto/README.md``. Requests and responses are
bincode (``application/x-bincode``), never JSON, except where the protocol only has JSON
(``/healthz``, ``/readyz``) or the body is a file (rig and clip uploads) or an image (renders);
motion graphs and joint maps are sent as JSON (their answers are bincode).
Crowd frames and meshes come back with their payloads decoded into arrays
(:mod:`crowdmorph.results`); the raw message stays reachable as ``.response``.

Extending: every call goes through :meth:`Client.request`, which sends one request on the kept
connection and turns error answers into :mod:`crowdmorph.errors` exceptions, and through
:func:`crowdmorph.wire.encode` / :func:`crowdmorph.wire.decode` for bodies. Session
streams are WebSockets, opened by :meth:`Client.stream` on a connection of their own (with
the optional ``websockets`` package) and decoded by :class:`crowdmorph.sessions.Viewer`.
"""

from __future__ import annotations

import base64
import http.client
import json
import os
import threading
import time
import urllib.parse
from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

from . import arrays as _arrays
from . import sessions as _sessions
from .errors import NotFound, ProtocolError, error_from_response
from .messages import (
    Alive,
    CameraSpec,
    ClipInfo,
    ClipList,
    ClipUpload,
    CrowdFrameRequest,
    BuiltGraph,
    CrowdFrameResponse,
    CrowdPoseResponse,
    GraphInfo,
    GraphList,
    GraphPlay,
    Head,
    HeadChange,
    ImageOptions,
    JointChannelSpec,
    JointMapInfo,
    JointMapSpec,
    LodInfo,
    LodLevelRequest,
    LodRequest,
    MeshResponse,
    OutputOptions,
    Placement,
    Readiness,
    RenderRequest,
    RigChannels,
    RigInfo,
    RigList,
    SessionHead,
    SessionInfo,
    SessionList,
    SessionPatch,
    SessionRequest,
    as_dict,
    as_head,
)
# The decoded results live in crowdmorph.results (crowdmorph.sessions makes them too); they are
# imported here as well, so that crowdmorph.client.Buffer and the like keep working.
from .results import Buffer, CrowdFrame, Image, Mesh
from .wire import DecodeError, decode, encode

__all__ = [
    "Client",
    "CrowdFrame",
    "Buffer",
    "Mesh",
    "Image",
    "Response",
    "self_contained_gltf",
    "BINCODE",
]

#: Content type of bincode bodies.
BINCODE = "application/x-bincode"

_VERSION = "0.1.0"

HeadLike = Union[Head, Mapping[str, Any], Sequence[Any]]
SessionHeadLike = Union[SessionHead, Mapping[str, Any], Sequence[Any]]
DataLike = Union[bytes, bytearray, memoryview, str, "os.PathLike[str]", Any]


class Response:
    """One HTTP answer: ``status``, ``headers`` (case-insensitive) and the whole ``body``."""

    __slots__ = ("status", "headers", "body", "wire_bytes")

    def __init__(self, status: int, headers: http.client.HTTPMessage, body: bytes):
        self.status = status
        self.headers = headers
        #: Bytes of the body as they came over the wire (before inflating).
        self.wire_bytes = len(body)
        self.body = _inflate(headers.get("content-encoding"), body)

    @property
    def content_type(self) -> str:
        return self.headers.get("content-type", "")

    @property
    def request_id(self) -> Optional[str]:
        return self.headers.get("x-request-id")


def _inflate(encoding: Optional[str], body: bytes) -> bytes:
    """``body`` inflated as its ``Content-Encoding`` says: none, gzip (standard library) or
    zstd (the optional ``zstandard`` package: ``pip install crowdmorph[zstd]``)."""
    enc = (encoding or "identity").strip().lower()
    if enc == "identity":
        return body
    if enc == "gzip":
        import gzip

        return gzip.decompress(body)
    if enc == "zstd":
        import zstandard  # type: ignore[import-not-found]

        return zstandard.ZstdDecompressor().decompressobj().decompress(body)
    raise ProtocolError(0, "bad_response", f"unknown Content-Encoding {encoding!r}")


def q16r_decode(planes: bytes, reference: bytes) -> bytes:
    """The q16 bytes (int16 little-endian) that ``q16r`` residual ``planes`` code against
    ``reference`` (``proto/README.md``, "Vertex data"): ``q = r + unzigzag(lo | hi << 8)``,
    wrapping (:func:`crowdmorph.arrays.q16r_decode`, with a length mismatch as a
    :class:`~crowdmorph.errors.ProtocolError`)."""
    try:
        return _arrays.q16r_decode(planes, reference)
    except ValueError as e:
        raise ProtocolError(0, "bad_response", str(e)) from None


def _zstd_available() -> bool:
    try:
        import zstandard  # type: ignore[import-not-found]  # noqa: F401
    except ImportError:
        return False
    return True


def _server_timing(value: Optional[str]) -> Dict[str, float]:
    out: Dict[str, float] = {}
    for part in (value or "").split(","):
        name, _, params = part.strip().partition(";")
        for p in params.split(";"):
            k, _, v = p.strip().partition("=")
            if k == "dur":
                try:
                    out[name.strip()] = float(v)
                except ValueError:
                    pass
    return out


def self_contained_gltf(path: Union[str, "os.PathLike[str]"]) -> bytes:
    """The bytes of a rig file as the server takes them: a GLB as it is, a ``.gltf`` with its
    external buffers and images inlined as base64 data URIs (the server reads no other
    files)."""
    with open(path, "rb") as f:
        data = f.read()
    if data[:4] == b"glTF":
        return data
    doc = json.loads(data)
    base = os.path.dirname(os.fspath(path))
    changed = False

    def image_mime(uri: str, entry: dict) -> str:
        named = "image/png" if uri.lower().endswith(".png") else "image/jpeg"
        return entry.get("mimeType") or named

    # Buffers are octet streams; an image keeps its MIME type (or one its name implies).
    for key, mime in (
        ("buffers", lambda uri, entry: "application/octet-stream"),
        ("images", image_mime),
    ):
        for entry in doc.get(key, []):
            uri = entry.get("uri")
            if not isinstance(uri, str) or uri.startswith("data:"):
                continue
            # glTF URIs are percent-encoded relative references.
            with open(os.path.join(base, urllib.parse.unquote(uri)), "rb") as f:
                payload = f.read()
            encoded = base64.b64encode(payload).decode("ascii")
            entry["uri"] = f"data:{mime(uri, entry)};base64,{encoded}"
            changed = True
    return json.dumps(doc).encode("utf-8") if changed else data


def _read_data(data: DataLike) -> Tuple[bytes, Optional[str]]:
    """Body bytes and, for a path, its file name (for the content type)."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return bytes(data), None
    if isinstance(data, (str, os.PathLike)):
        path = os.fspath(data)
        if path.lower().endswith(".gltf"):
            return self_contained_gltf(path), path
        with open(path, "rb") as f:
            return f.read(), path
    if hasattr(data, "read"):
        body = data.read()
        return (body.encode("utf-8") if isinstance(body, str) else bytes(body)), None
    raise TypeError(f"expected bytes, a path or a file object, not {type(data).__name__}")


def _is_gltf_json(body: bytes) -> bool:
    try:
        doc = json.loads(body)
    except ValueError:
        return False
    return isinstance(doc, dict) and "asset" in doc


def _rig_type(body: bytes) -> str:
    if body[:4] == b"glTF":
        return "model/gltf-binary"
    if body.lstrip()[:1] == b"{":
        return "model/gltf+json"
    return "application/octet-stream"


def _clip_type(body: bytes, path: Optional[str]) -> str:
    if body[:4] == b"glTF":
        return "model/gltf-binary"
    if body.lstrip()[:1] == b"{":
        return "model/gltf+json" if _is_gltf_json(body) else "application/json"
    if path is not None and path.lower().endswith(".csv"):
        return "text/csv"
    # The server sniffs octet-stream bodies: glTF magic, '{', else CSV.
    return "application/octet-stream"


def _of(cls: type, value: Any) -> Any:
    """``value`` as ``cls``: itself, or built from a dict."""
    if value is None or isinstance(value, cls):
        return value
    if isinstance(value, Mapping):
        return cls(**value)
    raise TypeError(f"expected {cls.__name__} or a dict, not {type(value).__name__}")


def _seg(s: str) -> str:
    """One path segment, percent-encoded (clip names may be any UTF-8)."""
    return urllib.parse.quote(s, safe="")


def _rig_hint(heads: Sequence[Any]) -> str:
    """The ``?rig=`` routing hint of a crowd: its first head's rig ("" without heads). The
    server ignores it; a load balancer hashing on it keeps each rig on one replica."""
    if not heads:
        return ""
    h = heads[0]
    if isinstance(h, Mapping):
        rig = h.get("rig")
    elif isinstance(h, (tuple, list)):
        rig = h[1] if len(h) > 1 else None
    else:
        rig = getattr(h, "rig", None)
    return f"?rig={_seg(rig)}" if isinstance(rig, str) and rig else ""


class Client:
    """A client of one crowdmorph server.

    ``Client("http://127.0.0.1:8080", token=None, timeout=300.0, arrays="auto")``. ``token`` is
    the admin token (sent as ``Authorization: Bearer``) that uploads, deletes, LOD changes and
    joint maps need when the server has one. ``arrays``: ``"auto"`` (numpy when installed),
    ``"numpy"`` or ``"python"`` (``array.array``). The client keeps one HTTP/1.1 connection
    alive across calls and reconnects when the server has closed it; calls from several
    threads take turns on it (use one client per thread for parallel requests). Use it as a
    context manager, or call :meth:`close`. ``timeout`` is the socket timeout in seconds (per
    send or receive); its default matches the server's deadline for uploads and LOD builds
    (``serve --admin-timeout-s``), which can take minutes for large rigs.

    Error answers raise :class:`~crowdmorph.errors.CrowdmorphError` subclasses; a server that
    cannot be reached raises the :class:`OSError` of the socket.
    """

    def __init__(
        self,
        url: str = "http://127.0.0.1:8080",
        token: Optional[str] = None,
        timeout: Optional[float] = 300.0,
        arrays: str = "auto",
        compression: Optional[str] = None,
    ):
        parts = urllib.parse.urlsplit(url if "://" in url else "http://" + url)
        if parts.scheme not in ("http", "https"):
            raise ValueError(f"unsupported URL scheme {parts.scheme!r} in {url!r} (http or https)")
        if not parts.hostname:
            raise ValueError(f"no host in {url!r}")
        self.url = url
        self.token = token
        self.timeout = timeout
        self.arrays = _arrays.resolve_backend(arrays)
        if compression not in (None, "gzip", "zstd"):
            raise ValueError(f"compression {compression!r}: gzip, zstd or None")
        if compression == "zstd" and not _zstd_available():
            raise ValueError("compression 'zstd' needs the zstandard package (crowdmorph[zstd])")
        #: ``Accept-Encoding`` asked for: ``None`` (plain bytes), ``"gzip"`` or ``"zstd"``.
        self.compression = compression
        self._scheme = parts.scheme
        self._host = parts.hostname
        self._port = parts.port
        self._prefix = parts.path.rstrip("/")
        self._conn: Optional[http.client.HTTPConnection] = None
        self._used = False
        self._lock = threading.Lock()
        #: ``x-request-id`` of the last answer (the server logs it).
        self.last_request_id: Optional[str] = None
        self._references: Dict[Any, bytes] = {}

    # -- connection ---------------------------------------------------------------------------

    def close(self) -> None:
        """Closes the kept connection (a later call opens a new one)."""
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _connection(self) -> http.client.HTTPConnection:
        if self._conn is None:
            cls = (
                http.client.HTTPSConnection
                if self._scheme == "https"
                else http.client.HTTPConnection
            )
            self._conn = cls(self._host, self._port, timeout=self.timeout)
            self._used = False
        return self._conn

    def request(
        self,
        method: str,
        path: str,
        body: Optional[bytes] = None,
        content_type: Optional[str] = None,
        accept: str = BINCODE,
        query: Optional[Mapping[str, Any]] = None,
        ok: Iterable[int] = (200,),
    ) -> Response:
        """Sends one request and returns the answer, raising for a status not in ``ok``.

        ``path`` starts with ``/`` and is appended to the URL's path; ``query`` values that are
        ``None`` are left out and booleans are sent as ``true``/``false``.
        """
        target = self._prefix + path
        if query:
            q = {
                k: ("true" if v is True else "false" if v is False else v)
                for k, v in query.items()
                if v is not None
            }
            if q:
                target += "?" + urllib.parse.urlencode(q)
        headers = {
            "Accept": accept,
            "User-Agent": f"crowdmorph-python/{_VERSION}",
            "Accept-Encoding": self.compression or "identity",
        }
        if content_type is not None:
            headers["Content-Type"] = content_type
        if self.token is not None:
            headers["Authorization"] = f"Bearer {self.token}"
        if body is None and method in ("POST", "PUT"):
            body = b""
        with self._lock:
            resp = self._send(method, target, body, headers)
        self.last_request_id = resp.request_id
        if resp.status not in ok:
            raise error_from_response(
                resp.status, resp.body, resp.headers.get("retry-after"), resp.request_id
            )
        return resp

    def _send(
        self, method: str, target: str, body: Optional[bytes], headers: Dict[str, str]
    ) -> Response:
        for attempt in (0, 1):
            conn = self._connection()
            reused = self._used
            try:
                try:
                    conn.request(method, target, body=body, headers=headers)
                except (ConnectionResetError, BrokenPipeError):
                    # A server that refuses a body early (413 body_too_large on a large
                    # upload) answers and closes before it has read everything: its answer
                    # is still there to read. Without one, the error below stands.
                    pass
                r = conn.getresponse()
                data = r.read()
            except (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError):
                # A kept-alive connection the server closed while it was idle (its
                # --idle-timeout-s) fails on first use; a fresh one is tried once.
                conn.close()
                self._conn = None
                if attempt == 0 and reused:
                    continue
                raise
            except BaseException:
                conn.close()
                self._conn = None
                raise
            self._used = True
            if r.will_close:
                conn.close()
                self._conn = None
            return Response(r.status, r.headers, data)
        raise AssertionError("unreachable")

    def _decode(self, cls: type, resp: Response) -> Any:
        if BINCODE not in resp.content_type:
            raise ProtocolError(
                resp.status,
                "bad_response",
                f"expected {BINCODE}, got {resp.content_type or 'no Content-Type'}",
                request_id=resp.request_id,
            )
        try:
            return decode(cls, resp.body)
        except DecodeError as e:
            raise ProtocolError(
                resp.status, "bad_response", f"{cls.__name__}: {e}", request_id=resp.request_id
            ) from e

    # -- health -------------------------------------------------------------------------------

    def healthz(self) -> Dict[str, Any]:
        """``GET /healthz``: ``{"status": "ok"}`` while the process serves."""
        return json.loads(self.request("GET", "/healthz", accept="application/json").body)

    def readyz(self) -> Readiness:
        """``GET /readyz``: engine, renderer and whether stored rigs are loaded (``status`` is
        ``loading`` until they are; that 503 is returned, not raised)."""
        resp = self.request("GET", "/readyz", accept="application/json", ok=(200, 503))
        try:
            obj = json.loads(resp.body)
            if resp.status == 503 and "error" in obj:
                raise error_from_response(
                    503, resp.body, resp.headers.get("retry-after"), resp.request_id
                )
            return Readiness.from_json(obj)
        except (ValueError, KeyError, TypeError) as e:
            raise ProtocolError(resp.status, "bad_response", f"readiness: {e}") from e

    def wait_ready(self, timeout: float = 30.0, interval: float = 0.05) -> Readiness:
        """Polls ``/readyz`` until the server has loaded its stored rigs (or ``timeout``)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                r = self.readyz()
                if r.status != "loading":
                    return r
            except (ConnectionError, http.client.HTTPException):
                if time.monotonic() >= deadline:
                    raise
            if time.monotonic() >= deadline:
                raise TimeoutError(f"server at {self.url} still loading after {timeout} s")
            time.sleep(interval)

    def metrics(self) -> str:
        """``GET /metrics``: OpenMetrics text (what Prometheus scrapes)."""
        return self.request("GET", "/metrics", accept="text/plain").body.decode("utf-8")

    # -- rigs ---------------------------------------------------------------------------------

    def rigs(self) -> List[RigInfo]:
        """``GET /v1/rigs``: every rig, ordered by id."""
        return self._decode(RigList, self.request("GET", "/v1/rigs")).rigs

    def rig(self, rig: str) -> RigInfo:
        """``GET /v1/rigs/{id}``."""
        return self._decode(RigInfo, self.request("GET", f"/v1/rigs/{_seg(rig)}"))

    def upload_rig(
        self,
        data: DataLike,
        name: Optional[str] = None,
        *,
        content_type: Optional[str] = None,
        replace: bool = False,
    ) -> RigInfo:
        """``POST /v1/rigs?name=ID``: uploads a GLB or glTF rig and returns its description.

        ``data`` is the file's bytes, a path (a ``.gltf``'s external buffers are inlined) or a
        binary file object. Name it: without ``name`` its id is ``rig``. ``replace=True``
        deletes an existing rig of that id first (not atomic: between the two a request for
        it gets 404).
        """
        body, _ = _read_data(data)
        if replace:
            if name is None:
                raise ValueError("replace=True needs the rig's name")
            try:
                self.delete_rig(name)
            except NotFound:
                pass
        resp = self.request(
            "POST",
            "/v1/rigs",
            body,
            content_type or _rig_type(body),
            query={"name": name},
            ok=(201,),
        )
        return self._decode(RigInfo, resp)

    def delete_rig(self, rig: str) -> None:
        """``DELETE /v1/rigs/{id}`` (the embedded rig cannot be deleted: 403)."""
        self.request("DELETE", f"/v1/rigs/{_seg(rig)}", ok=(204,))

    def mesh(self, rig: str, lod: int = 0) -> Mesh:
        """``GET /v1/rigs/{id}/mesh?lod=L``: topology and neutral pose of level ``lod``'s mesh
        (the vertex order of that level's crowd-frame buffers)."""
        resp = self.request("GET", f"/v1/rigs/{_seg(rig)}/mesh", query={"lod": lod})
        return Mesh(self._decode(MeshResponse, resp), self.arrays)

    def materials(self, rig: str) -> Dict[str, Any]:
        """``GET /v1/rigs/{id}/materials``: the rig's glTF ``materials``, ``textures``,
        ``samplers`` and ``images`` (each with a ``uri`` for :meth:`texture_at`), its
        ``extensionsUsed`` and the import's ``notes``, as a dict (empty lists without)."""
        resp = self.request("GET", f"/v1/rigs/{_seg(rig)}/materials", accept="application/json")
        return json.loads(resp.body)

    def texture(self, rig: str, image: int) -> Tuple[bytes, str]:
        """``GET /v1/rigs/{id}/textures/{i}``: image ``i``'s bytes and content type."""
        return self.texture_at(f"/v1/rigs/{_seg(rig)}/textures/{int(image)}")

    def model_glb(self, rig: str, lod: int = 0) -> bytes:
        """``GET /v1/rigs/{id}/model.glb?lod=L``: level ``lod``'s mesh as a GLB with its
        materials and images, no morph targets (what an engine loads once)."""
        resp = self.request(
            "GET", f"/v1/rigs/{_seg(rig)}/model.glb", accept="*/*", query={"lod": lod}
        )
        return resp.body

    def texture_at(self, uri: str) -> Tuple[bytes, str]:
        """An image by the ``uri`` :meth:`materials` gives it: bytes and content type."""
        path, _, query = uri.partition("?")
        q = dict(p.split("=", 1) for p in query.split("&") if "=" in p)
        resp = self.request("GET", path, accept="*/*", query=q or None)
        return resp.body, resp.headers.get("content-type", "")

    def lod(self, rig: str) -> LodInfo:
        """``GET /v1/rigs/{id}/lod``."""
        return self._decode(LodInfo, self.request("GET", f"/v1/rigs/{_seg(rig)}/lod"))

    def set_lod(
        self,
        rig: str,
        request: Optional[LodRequest] = None,
        *,
        method: Optional[str] = None,
        order: Optional[Sequence[str]] = None,
        pinned: Sequence[str] = (),
        levels: Optional[Sequence[Any]] = None,
        mesh_fractions: Sequence[float] = (),
    ) -> RigInfo:
        """``PUT /v1/rigs/{id}/lod``: rebuilds the rig's level of detail.

        Pass a :class:`~crowdmorph.messages.LodRequest`, or its fields: ``levels`` items are
        :class:`~crowdmorph.messages.LodLevelRequest`, ``(shapes, mesh)`` pairs or shape
        counts. Returns the rig with its new LOD (``lod.status`` may be ``computing``:
        :meth:`wait_lod` waits for it).
        """
        if request is None:
            lv = None
            if levels is not None:
                lv = []
                for level in levels:
                    if isinstance(level, LodLevelRequest):
                        lv.append(level)
                    elif isinstance(level, int):
                        lv.append(LodLevelRequest(level))
                    else:
                        lv.append(LodLevelRequest(*level))
            request = LodRequest(
                method=method,
                order=None if order is None else list(order),
                pinned=list(pinned),
                levels=lv,
                mesh_fractions=list(mesh_fractions),
            )
        resp = self.request("PUT", f"/v1/rigs/{_seg(rig)}/lod", encode(request), BINCODE)
        return self._decode(RigInfo, resp)

    def wait_lod(self, rig: str, timeout: float = 60.0, interval: float = 0.1) -> LodInfo:
        """Polls the rig's LOD until it is no longer ``computing`` (or ``timeout``)."""
        deadline = time.monotonic() + timeout
        while True:
            info = self.lod(rig)
            if info.status != "computing":
                return info
            if time.monotonic() >= deadline:
                raise TimeoutError(
                    f"LOD of {rig!r} still computing after {timeout} s ({info.progress:.0%})"
                )
            time.sleep(interval)

    # -- clips --------------------------------------------------------------------------------

    def upload_clip(
        self,
        rig: str,
        data: Union[DataLike, Mapping[str, Any]],
        name: Optional[str] = None,
        *,
        content_type: Optional[str] = None,
        fps: Optional[float] = None,
        ignore_unknown: bool = False,
    ) -> ClipUpload:
        """``POST /v1/rigs/{id}/clips?name=NAME``: adds clips from CSV, a JSON clip or glTF.

        ``data`` is bytes, a path, a binary file object, or a dict (a JSON clip:
        ``{"fps": 30, "targets": [...], "frames": [[...], ...]}``). The content type is
        inferred (glTF magic, JSON, ``.csv``) unless given. With ``ignore_unknown`` target
        names the rig lacks are reported in ``ignored`` instead of refused.
        """
        if isinstance(data, Mapping):
            body, path = json.dumps(data).encode("utf-8"), None
            content_type = content_type or "application/json"
        else:
            body, path = _read_data(data)
        resp = self.request(
            "POST",
            f"/v1/rigs/{_seg(rig)}/clips",
            body,
            content_type or _clip_type(body, path),
            query={
                "name": name,
                "fps": fps,
                "ignore_unknown": True if ignore_unknown else None,
            },
            ok=(201,),
        )
        return self._decode(ClipUpload, resp)

    def clips(self, rig: str) -> List[ClipInfo]:
        """``GET /v1/rigs/{id}/clips``."""
        return self._decode(ClipList, self.request("GET", f"/v1/rigs/{_seg(rig)}/clips")).clips

    def clip(self, rig: str, name: str) -> ClipInfo:
        """``GET /v1/rigs/{id}/clips/{name}``."""
        return self._decode(
            ClipInfo, self.request("GET", f"/v1/rigs/{_seg(rig)}/clips/{_seg(name)}")
        )

    def delete_clip(self, rig: str, name: str) -> None:
        """``DELETE /v1/rigs/{id}/clips/{name}`` (the embedded rig's own clips: 403)."""
        self.request("DELETE", f"/v1/rigs/{_seg(rig)}/clips/{_seg(name)}", ok=(204,))

    # -- joint maps ---------------------------------------------------------------------------

    def joint_map(self, rig: str) -> JointMapInfo:
        """``GET /v1/rigs/{id}/joint-map``: which clip columns turn which joints of the rig
        (its own map, or with ``default`` true the defaults: Live Link Face's ``HeadYaw``, ...,
        ``RightEyeRoll`` onto the head and eye joints it has)."""
        return self._decode(JointMapInfo, self.request("GET", f"/v1/rigs/{_seg(rig)}/joint-map"))

    def set_joint_map(
        self,
        rig: str,
        channels: Union[
            JointMapSpec,
            Mapping[str, Any],
            Iterable[Union[JointChannelSpec, Mapping[str, Any]]],
        ],
    ) -> JointMapInfo:
        """``PUT /v1/rigs/{id}/joint-map``: makes ``channels`` the rig's own map (stored with
        the rig; clips uploaded afterwards are read with it, clips already there keep their
        joint tables). ``channels`` is a :class:`~crowdmorph.messages.JointMapSpec`, its JSON
        form (``{"channels": [...]}``), or a list of
        :class:`~crowdmorph.messages.JointChannelSpec` objects or dicts with its keys
        (``{"column": "HeadYaw", "node": "Neck", "axis": [1, 0, 0], "scale": 0.5}``; ``axis``
        defaults to +Y, ``scale`` to 1 radian per unit). Returns the map in force, axes
        normalized. Needs the admin token when the server has one; a node the skeleton lacks
        raises :class:`~crowdmorph.errors.BadRequest` ``unknown_joints``, a bad axis, scale or
        column (or a rig without a skeleton) ``invalid_joint_map``."""
        if isinstance(channels, JointMapSpec):
            items: Iterable[Any] = channels.channels
        elif isinstance(channels, Mapping):
            if set(channels) != {"channels"}:
                raise ValueError(
                    "a joint map as a dict is its JSON form, {\"channels\": [...]}, not "
                    f"{sorted(channels)!r}"
                )
            items = channels["channels"]
        elif isinstance(channels, (str, bytes)):
            raise TypeError("a joint map is a JointMapSpec or a list of channels, not a string")
        else:
            items = channels
        spec = JointMapSpec(channels=[_joint_channel(c) for c in items])
        resp = self.request(
            "PUT",
            f"/v1/rigs/{_seg(rig)}/joint-map",
            json.dumps(as_dict(spec)).encode(),
            "application/json",
        )
        return self._decode(JointMapInfo, resp)

    def reset_joint_map(self, rig: str) -> JointMapInfo:
        """``DELETE /v1/rigs/{id}/joint-map``: back to the default map; returns it. Needs the
        admin token when the server has one."""
        resp = self.request("DELETE", f"/v1/rigs/{_seg(rig)}/joint-map")
        return self._decode(JointMapInfo, resp)

    # -- crowds -------------------------------------------------------------------------------

    def crowd_frame(
        self,
        heads: Iterable[HeadLike],
        format: str = "f32",
        normals: bool = False,
        wrap: bool = True,
        *,
        decode: bool = True,
    ) -> Any:
        """``POST /v1/crowd/frame``: blends a crowd.

        ``heads`` are :class:`~crowdmorph.messages.Head` objects, dicts with the same keys, or
        ``(head, rig, clip, frame[, lod])`` tuples; on a rig with a skeleton a head's
        ``joints`` (``{"LeftEye": JointTransform(rotation=[0, 0.17, 0, 0.985])}``) sets named
        nodes' local transforms over its clip's pose. ``format`` is ``"f32"`` (exact),
        ``"f16"`` or ``"q16"`` (half the bytes; q16 is dequantized with the box each buffer
        carries), or ``"q16r"``: q16 positions as residuals against the rig's neutral (the
        same values, bytes that compress well: ask for ``compression`` too); the client fetches
        each (rig, LOD, box)'s reference once and decodes them to q16. Returns a
        :class:`CrowdFrame` with arrays, or with ``decode=False`` the raw
        :class:`~crowdmorph.messages.CrowdFrameResponse` (payloads as bytes; q16r positions
        still residual planes).
        """
        if format == "weights":
            raise ValueError("format 'weights' answers with poses, not buffers: use crowd_poses()")
        if format not in ("f32", "f16", "q16", "q16r"):
            raise ValueError(f"format must be 'f32', 'f16', 'q16' or 'q16r', not {format!r}")
        req = CrowdFrameRequest(
            heads=heads if isinstance(heads, (list, tuple)) else list(heads),
            output=OutputOptions(normals=bool(normals), format=format),
            wrap=bool(wrap),
        )
        path = "/v1/crowd/frame" + _rig_hint(req.heads)
        resp = self.request("POST", path, encode(req), BINCODE)
        frame = self._decode(CrowdFrameResponse, resp)
        if not decode:
            return frame
        if frame.format == "q16r":
            for b in frame.buffers:
                b.positions = q16r_decode(bytes(b.positions), self.q16_reference(b))
            frame.format = "q16"
        try:
            return CrowdFrame(frame, self.arrays)
        except ValueError as e:
            raise ProtocolError(
                resp.status, "bad_response", str(e), request_id=resp.request_id
            ) from e

    def crowd_poses(self, heads: Iterable[HeadLike], wrap: bool = True) -> CrowdPoseResponse:
        """``POST /v1/crowd/frame`` with ``"format": "weights"``, for a client that blends
        itself: per unique head its final weights (``pose.weights_f32()``, one per channel of
        :meth:`rig_channels`) and the skeleton nodes its pose moves (``pose.joints``); each
        request head's pose is ``poses[heads[i].buffer]``. No vertices are computed. A head
        with a ``lod`` other than 0 raises :class:`~crowdmorph.errors.BadRequest`
        ``invalid_output``."""
        req = CrowdFrameRequest(
            heads=heads if isinstance(heads, (list, tuple)) else list(heads),
            output=OutputOptions(normals=False, format="weights"),
            wrap=bool(wrap),
        )
        path = "/v1/crowd/frame" + _rig_hint(req.heads)
        resp = self.request("POST", path, encode(req), BINCODE)
        return self._decode(CrowdPoseResponse, resp)

    def rig_channels(self, rig: str) -> RigChannels:
        """``GET /v1/rigs/{id}/channels``: the rig's weight channels and skeleton nodes, in
        the order a pose (:meth:`crowd_poses`, a ``output="weights"`` viewer) numbers them."""
        return self._decode(RigChannels, self.request("GET", f"/v1/rigs/{_seg(rig)}/channels"))

    def q16_reference(self, buffer: Any) -> bytes:
        """The q16 reference of a ``q16r`` buffer (its rig, LOD and box): the q16 positions of
        the frame with every weight 0, fetched once and kept."""
        q = buffer.quantization
        key = (buffer.rig, buffer.lod, tuple(q.min), tuple(q.step)) if q else None
        cache = self._references
        if key not in cache:
            heads = [Head(head=0, rig=buffer.rig, lod=buffer.lod, weights={})]
            ref = self.crowd_frame(heads, format="q16", decode=False).buffers[0]
            cache[key] = bytes(ref.positions)
        return cache[key]

    # -- motion graphs ------------------------------------------------------------------------

    def put_graph(self, rig: str, name: str, graph: Any) -> GraphInfo:
        """``PUT /v1/rigs/{rig}/graphs/{name}``: stores a motion graph (a :class:`MotionGraph`
        or a dict in its JSON form: ``{"nodes": [...], "edges": [{"from": ..., ...}]}``)."""
        body = graph if isinstance(graph, Mapping) else as_dict(graph)
        resp = self.request(
            "PUT",
            f"/v1/rigs/{_seg(rig)}/graphs/{_seg(name)}",
            json.dumps(body).encode(),
            "application/json",
        )
        return self._decode(GraphInfo, resp)

    def build_graph(
        self,
        rig: str,
        name: str,
        window: Optional[int] = None,
        threshold: Optional[float] = None,
    ) -> BuiltGraph:
        """``POST /v1/rigs/{rig}/graphs/{name}?auto=1``: builds a motion graph from the rig's
        clips (Kovar et al.: transitions where frames match in vertex space), stores it, and
        returns it with each edge's cost."""
        resp = self.request(
            "POST",
            f"/v1/rigs/{_seg(rig)}/graphs/{_seg(name)}",
            query={"auto": 1, "window": window, "threshold": threshold},
        )
        return self._decode(BuiltGraph, resp)

    def graphs(self, rig: str) -> List[GraphInfo]:
        """``GET /v1/rigs/{rig}/graphs``."""
        return self._decode(GraphList, self.request("GET", f"/v1/rigs/{_seg(rig)}/graphs")).graphs

    def delete_graph(self, rig: str, name: str) -> None:
        """``DELETE /v1/rigs/{rig}/graphs/{name}``."""
        self.request("DELETE", f"/v1/rigs/{_seg(rig)}/graphs/{_seg(name)}", ok=(204,))

    def live_frame(
        self,
        rig: str,
        weights: Any,
        *,
        lod: int = 0,
        format: str = "f32",
        normals: bool = False,
    ) -> Any:
        """``POST /v1/crowd/frame`` for faces driven by live weights (a face tracker's, an
        Audio2Face-style service's): ``weights`` is one face — a dict of weights by target
        name (ARKit's names match loosely, e.g. ``eyeBlink_L``; names left out are 0) or a
        sequence of one weight per ``RigInfo.targets`` name — or a list of such faces. Head
        ``i`` is face ``i``; faces whose weights agree to 1/4096 share one buffer."""
        one = isinstance(weights, Mapping) or (
            isinstance(weights, Sequence) and all(isinstance(w, (int, float)) for w in weights)
        )
        faces = [weights] if one else list(weights)
        heads = [Head(head=i, rig=rig, lod=lod, weights=f) for i, f in enumerate(faces)]
        return self.crowd_frame(heads, format=format, normals=normals)

    def render(
        self,
        heads: Iterable[HeadLike],
        *,
        wrap: bool = True,
        placements: Optional[Sequence[Union[Placement, Mapping[str, Any]]]] = None,
        camera: Optional[Union[CameraSpec, Mapping[str, Any]]] = None,
        image: Optional[Union[ImageOptions, Mapping[str, Any]]] = None,
        width: Optional[int] = None,
        height: Optional[int] = None,
        format: Optional[str] = None,
        quality: Optional[int] = None,
        background: Optional[Sequence[int]] = None,
    ) -> Image:
        """``POST /v1/crowd/render``: a picture of the crowd, as :class:`Image` bytes.

        ``placements`` and ``camera`` as in ``proto/README.md`` (objects or dicts); the image
        options either as ``image=`` or as the keywords ``width``, ``height``, ``format``
        (``png``, ``jpeg``, ``rgba``), ``quality`` and ``background``. Defaults: heads on a
        grid, a front camera, 640 × 480 PNG.
        """
        opts = _of(ImageOptions, image)
        extra = {
            k: v
            for k, v in (
                ("width", width),
                ("height", height),
                ("format", format),
                ("quality", quality),
                ("background", None if background is None else list(background)),
            )
            if v is not None
        }
        if extra:
            if opts is not None:
                raise ValueError("give the image options either as image= or as keywords")
            opts = ImageOptions(**extra)
        req = RenderRequest(
            heads=heads if isinstance(heads, (list, tuple)) else list(heads),
            wrap=bool(wrap),
            placements=None if placements is None else [_of(Placement, p) for p in placements],
            camera=_of(CameraSpec, camera),
            image=opts,
        )
        path = "/v1/crowd/render" + _rig_hint(req.heads)
        if req.camera is not None and req.camera.frame is not None:
            # A framing camera is JSON-only (bincode's CameraSpec is pinned): the whole
            # request goes as JSON.
            req.heads = [as_head(h) for h in req.heads]
            body, content_type = json.dumps(as_dict(req)).encode(), "application/json"
        else:
            body, content_type = encode(req), BINCODE
        resp = self.request("POST", path, body, content_type, accept="image/*, */*")
        img = Image(resp.body)
        img.content_type = resp.content_type
        try:
            img.width = int(resp.headers.get("x-image-width", "0"))
            img.height = int(resp.headers.get("x-image-height", "0"))
        except ValueError as e:
            raise ProtocolError(resp.status, "bad_response", f"image size header: {e}") from e
        img.server_timing = _server_timing(resp.headers.get("server-timing"))
        return img

    # -- sessions -----------------------------------------------------------------------------

    def create_session(
        self,
        heads: Iterable[SessionHeadLike],
        fps: float = 30.0,
        wrap: bool = True,
        idle_timeout_s: int = 60,
        id: Optional[str] = None,
        alive: Optional[Union[Alive, Mapping[str, Any]]] = None,
    ) -> SessionInfo:
        """``POST /v1/sessions``: a crowd the server advances ``fps`` times a second and
        streams to viewers (:meth:`stream`). Needs the admin token when the server has one.
        With ``id`` (1-64 of ``A-Z a-z 0-9 . _ -``) it is ``PUT /v1/sessions/{id}``: the
        session gets that id, so a load balancer hashing on it sends every viewer to the same
        replica; an id that is taken raises ``Conflict`` (``session_exists``).

        ``heads`` are :class:`~crowdmorph.messages.SessionHead` objects, dicts with its keys
        (``graph`` and ``joints`` included: a :class:`~crowdmorph.messages.GraphPlay` or its
        dict, and joint overrides as for crowd frames),
        or ``(head, rig, clip[, offset[, position[, yaw[, scale]]]])`` tuples. At tick ``t``
        a head plays frame ``offset + floor((t - 1) * clip_fps / fps)``, looping when
        ``wrap`` (else holding the last frame). The session ends ``idle_timeout_s`` seconds
        after its last viewer leaves. A head with an empty ``clip`` and no graph shows its
        rig's neutral (a rig with no clips). ``alive`` (an :class:`~crowdmorph.messages.Alive`
        or its dict, e.g. ``{"blink": True, "look_at": [0, 1.6, 3]}``) makes every head
        without its own ``alive`` blink, dart its eyes, look at a point or breathe.
        """
        req = SessionRequest(
            fps=float(fps),
            wrap=bool(wrap),
            idle_timeout_s=int(idle_timeout_s),
            heads=[_session_head(h) for h in heads],
            alive=alive,
        )
        if id is None:
            resp = self.request("POST", "/v1/sessions", encode(req), BINCODE, ok=(201,))
        else:
            resp = self.request("PUT", f"/v1/sessions/{_seg(id)}", encode(req), BINCODE, ok=(201,))
        return self._decode(SessionInfo, resp)

    def sessions(self) -> List[SessionInfo]:
        """``GET /v1/sessions``: every session, ordered by id."""
        return self._decode(SessionList, self.request("GET", "/v1/sessions")).sessions

    def session(self, session: str) -> SessionInfo:
        """``GET /v1/sessions/{id}``: heads, viewers, the last tick and the counters."""
        return self._decode(SessionInfo, self.request("GET", f"/v1/sessions/{_seg(session)}"))

    def patch_session(
        self,
        session: str,
        add: Iterable[SessionHeadLike] = (),
        remove: Iterable[int] = (),
        change: Iterable[Union[HeadChange, Mapping[str, Any]]] = (),
        alive: Optional[Union[Alive, Mapping[str, Any]]] = None,
    ) -> SessionInfo:
        """``PATCH /v1/sessions/{id}``: removes, changes and adds heads, together, at the next
        tick (in that order). ``change`` items are :class:`~crowdmorph.messages.HeadChange`
        objects or dicts (``{"head": 2, "clip": "smile", "yaw": 90}``; absent fields stay;
        ``"joints"`` replaces the head's joint overrides, ``{}`` clears them).
        ``alive`` replaces the session's liveliness (a patch with only ``alive``, e.g. a
        look-at point moved every tick, copies no head).
        Returns the session with its heads as they will be at the next tick."""
        patch = SessionPatch(
            remove=[int(h) for h in remove],
            change=[_of(HeadChange, c) for c in change],
            add=[_session_head(h) for h in add],
            alive=alive,
        )
        resp = self.request(
            "PATCH", f"/v1/sessions/{_seg(session)}", encode(patch), BINCODE
        )
        return self._decode(SessionInfo, resp)

    def send_live(self, session: str, heads: Iterable[Mapping[str, Any]]) -> int:
        """``POST /v1/sessions/{id}/live``: one message of live input, a dict per sample
        (``{"head": 3, "weights": {"jawOpen": 0.4}, "t": 12.5}``; ``joints`` by node name,
        rotations only). The heads must be live (``SessionHead.live``). Needs the admin token
        when the server has one. Returns how many samples the server took; a rate past the
        server's ``--max-live-rate`` raises with code ``live_rate_exceeded``. For a stream of
        them, a WebSocket at the same path takes the same messages."""
        body = json.dumps({"heads": [dict(h) for h in heads]}).encode()
        resp = self.request(
            "POST",
            f"/v1/sessions/{_seg(session)}/live",
            body,
            "application/json",
            accept="application/json",
        )
        return int(json.loads(resp.body)["accepted"])

    def delete_session(self, session: str) -> None:
        """``DELETE /v1/sessions/{id}``: ends it; its viewers are closed with 1001."""
        self.request("DELETE", f"/v1/sessions/{_seg(session)}", ok=(204,))

    def stream(
        self,
        session: str,
        format: str = "q16",
        normals: bool = False,
        lod: Union[int, Sequence[Sequence[float]], Mapping[str, Any]] = 0,
        camera: Optional[Union[CameraSpec, Mapping[str, Any]]] = None,
        output: str = "vertices",
        image: Optional[Union[ImageOptions, Mapping[str, Any]]] = None,
        *,
        temporal: bool = False,
        keyframe_every: Optional[int] = None,
        compression: Optional[str] = None,
        tolerance: Optional[float] = None,
        timeout: Optional[float] = None,
        max_message: Optional[int] = 1 << 31,
    ) -> _sessions.Viewer:
        """Watches a session: opens ``GET /v1/sessions/{id}/stream`` (a WebSocket on its own
        connection), sends the hello and returns a :class:`~crowdmorph.sessions.Viewer`, an
        iterator of :class:`~crowdmorph.sessions.Tick` (every head's current positions, with
        "unchanged" applied) or, for ``output="frames"``,
        :class:`~crowdmorph.sessions.StreamFrame` images.

        Needs the ``websockets`` package (11 or later): ``pip install 'crowdmorph[sessions]'``;
        without it this raises :class:`ImportError` saying so (the rest of the client works
        without it).

        ``format`` (``f32``, ``f16``, ``q16``) and ``normals`` as for crowd frames; ``lod`` is a
        level for every head or ``[[metres, level], ...]`` by distance from ``camera``
        (a :class:`~crowdmorph.messages.CameraSpec` or dict; needed for LOD by distance and
        images); ``image`` the :class:`~crowdmorph.messages.ImageOptions` of frames.
        ``temporal=True`` (q16 vertices only) has the server send each head's buffer as
        residuals against the last one this viewer received for it, with a keyframe at
        least every ``keyframe_every`` ticks (server default 60); ``compression``
        (``"deflate"`` or ``"zstd"``, the latter needing ``pip install 'crowdmorph[zstd]'``)
        has it compress every message. Both are decoded here: the ticks are bit for bit a
        plain q16 viewer's (plus ``wire_bytes``, ``keyframes`` and ``from_residuals``).
        ``tolerance`` (near-clones, with a ``camera``): a head ``d`` metres from the eye may
        be off by ``tolerance × d`` of its rig's diagonal, so that far heads whose poses
        differ by less are computed once.
        ``output="weights"`` (for a client that blends itself) yields
        :class:`~crowdmorph.sessions.PoseTick` objects instead: per head its final weights
        and moved joints (:meth:`rig_channels` names them), no vertices; ``format``,
        ``normals``, ``lod`` and ``temporal`` do not apply to it.
        ``timeout`` (seconds; default: the client's) bounds the opening handshake and each
        wait for a message; ``max_message`` is the largest message taken, in bytes (``None``:
        no limit; a larger one closes the stream with 1009). An unknown session raises
        :class:`~crowdmorph.errors.NotFound`; a hello the server refuses raises
        :class:`~crowdmorph.errors.StreamClosed` (1008 with the reason) from the iteration.
        """
        settings = _sessions.hello(
            format,
            normals,
            lod,
            camera,
            output,
            image,
            temporal=temporal,
            keyframe_every=keyframe_every,
            compression=compression,
            tolerance=tolerance,
        )
        host = f"[{self._host}]" if ":" in self._host else self._host
        netloc = host if self._port is None else f"{host}:{self._port}"
        scheme = "wss" if self._scheme == "https" else "ws"
        return _sessions.open_viewer(
            f"{scheme}://{netloc}{self._prefix}/v1/sessions/{_seg(session)}/stream",
            session,
            settings,
            self.arrays,
            token=self.token,
            user_agent=f"crowdmorph-python/{_VERSION}",
            timeout=self.timeout if timeout is None else timeout,
            max_message=max_message,
        )


def _joint_channel(c: Union[JointChannelSpec, Mapping[str, Any]]) -> JointChannelSpec:
    """A joint map channel from a :class:`JointChannelSpec` or a dict with its keys (``axis``
    and ``scale`` optional; other keys are an error, as on the server)."""
    if isinstance(c, JointChannelSpec):
        ch = c
    elif isinstance(c, Mapping):
        ch = JointChannelSpec(**c)
    else:
        raise TypeError(f"a joint channel is a JointChannelSpec or a dict, not {c!r}")
    axis = [float(x) for x in ch.axis]
    if len(axis) != 3:
        raise ValueError(f"channel {ch.column!r}: an axis has 3 components, not {len(axis)}")
    return JointChannelSpec(ch.column, ch.node, axis, float(ch.scale))


def _session_head(h: SessionHeadLike) -> SessionHead:
    """A session head from a :class:`SessionHead`, a dict or a tuple."""
    if isinstance(h, SessionHead):
        return h
    if isinstance(h, Mapping):
        h = dict(h)
        if h.get("graph") is not None:
            h["graph"] = _of(GraphPlay, h["graph"])
        # "joints" (dicts by node name) become JointTransform objects in SessionHead itself.
        return SessionHead(**h)
    if isinstance(h, (tuple, list)) and 3 <= len(h) <= 7:
        fields = list(h)
        if len(fields) > 4:
            fields[4] = [float(x) for x in fields[4]]
        return SessionHead(*fields)
    raise TypeError(
        "a session head is a SessionHead, a dict or a "
        f"(head, rig, clip[, offset[, position[, yaw[, scale]]]]) tuple, not {h!r}"
    )

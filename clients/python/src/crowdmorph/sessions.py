"""Session viewers: a crowd session's WebSocket stream, decoded into what a viewer draws.

:meth:`crowdmorph.Client.stream` opens ``GET /v1/sessions/{id}/stream``, sends the JSON hello
and returns a :class:`Viewer`. Iterating it yields one :class:`Tick` per binary message (or a
:class:`StreamFrame` for ``output="frames"``). The server sends only what changed for this
viewer: a layout when the session's heads changed, and buffers only for heads whose
(rig, clip, frame, LOD) changed, the others marked ``HEAD_UNCHANGED`` ("keep what you had") or
``HEAD_MISSING`` ("draw nothing"). The viewer applies those marks, so that each tick carries
every head's current positions (and normals), as drawing code wants them.

The server drops ticks a slow viewer has not read yet and sends the newest one instead, so
tick numbers may skip; "unchanged" always refers to the message this viewer last received, so
applying the messages in order is always right.

A q16 viewer may ask for ``temporal`` buffers (``TickDelta`` messages: a head's buffer as
residuals against the last buffer it received for that head, with a keyframe at least every
``keyframe_every`` ticks) and for ``compression`` (``"deflate"``, the standard library's zlib,
or ``"zstd"``, the optional ``zstandard`` package: ``pip install 'crowdmorph[zstd]'``) of every
message. The viewer decodes both: its ticks are the same, bit for bit, as a plain q16 viewer's.

The WebSocket is the ``websockets`` package's synchronous client (version 11 or later), an
optional dependency: ``pip install 'crowdmorph[sessions]'``. It is imported only when a
stream is opened, so the rest of the package needs nothing but the standard library.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import threading
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Union

from . import arrays as _arrays
from .errors import ProtocolError, StreamClosed, error_from_response
from .messages import (
    HEAD_MISSING,
    HEAD_UNCHANGED,
    MESSAGE_ENCODINGS,
    CameraSpec,
    ImageOptions,
    PackedMessage,
    SessionHead,
    TickDelta,
    TickFrame,
    TickPoses,
    TickVertices,
    _zstandard,
    as_dict,
    decode_stream_message,
    unpack_stream_message,
)
from .results import Buffer, Image
from .wire import DecodeError

__all__ = [
    "Viewer",
    "Tick",
    "PoseTick",
    "StreamFrame",
    "open_viewer",
    "hello",
    "lod_json",
    "camera_json",
]

#: What to install when the WebSocket library is missing (or older than 11).
INSTALL_HINT = "pip install 'crowdmorph[sessions]' (or pip install 'websockets>=11')"

_CONTENT_TYPES = {"png": "image/png", "jpeg": "image/jpeg", "rgba": "application/octet-stream"}


class Tick:
    """One tick as a viewer draws it, after applying "unchanged" and "missing".

    - ``tick``: the session's tick number (from 1; later ticks may be skipped for a slow
      viewer), ``format`` and ``normals`` of the buffers, ``timings`` (microseconds).
    - ``layout``: the session's heads (:class:`~crowdmorph.messages.SessionHead`: rig, clip,
      offset, position, yaw, scale, graph, joints) in stream order; ``layout_changed`` is true
      when this message carried a new one (always for the first).
    - ``positions`` / ``normals``: head id → its current array (numpy ``(vertices, 3)``
      float32, or a flat ``array('f')``), for every head that has something to draw; clones
      share one array. ``normals`` is empty unless the viewer asked for them.
    - ``buffers``: head id → the :class:`~crowdmorph.results.Buffer` drawn (its ``rig``,
      ``clip``, ``frame`` played and ``lod``).
    - ``changed``: ids whose buffer this message brought; ``missing``: ids with nothing to
      draw (their rig or clip was deleted).
    - ``message``: the raw :class:`~crowdmorph.messages.TickVertices` (or, for a ``temporal``
      viewer, :class:`~crowdmorph.messages.TickDelta`, whose residual buffers are still
      residual planes; decompressed when it came packed).
    - ``wire_bytes``: bytes of the WebSocket message as received (compressed, when the viewer
      asked for ``compression``); ``compression``: ``"zstd"``, ``"deflate"`` or ``None``.
    - ``keyframes`` / ``from_residuals``: of the ``changed`` heads, how many got a plain buffer
      and how many one decoded from residuals against their previous buffer (always 0 unless
      the viewer asked for ``temporal``).
    """

    __slots__ = (
        "tick",
        "format",
        "normals_included",
        "layout",
        "layout_changed",
        "positions",
        "normals",
        "buffers",
        "changed",
        "missing",
        "timings",
        "message",
        "wire_bytes",
        "compression",
        "keyframes",
        "from_residuals",
    )

    def __init__(self, **kw: Any):
        for k, v in kw.items():
            setattr(self, k, v)

    @property
    def heads(self) -> List[int]:
        """Head ids in layout order."""
        return [h.head for h in self.layout]

    def __repr__(self) -> str:
        return (
            f"Tick({self.tick}, format={self.format!r}, heads={len(self.layout)}, "
            f"changed={len(self.changed)}, missing={len(self.missing)}"
            f"{', new layout' if self.layout_changed else ''})"
        )


class PoseTick:
    """One tick of a viewer that asked for ``output="weights"``, after applying "unchanged":
    ``tick``, ``layout`` (and ``layout_changed``), ``poses`` (head id →
    :class:`~crowdmorph.messages.HeadPose`: its binary16 weights, ``weights_f32()``, and moved
    joints; clones share one), ``changed`` and ``missing`` ids, ``timings``, the raw
    :class:`~crowdmorph.messages.TickPoses` as ``message`` and ``wire_bytes``."""

    __slots__ = (
        "tick",
        "layout",
        "layout_changed",
        "poses",
        "changed",
        "missing",
        "timings",
        "message",
        "wire_bytes",
    )

    def __init__(self, **kw: Any):
        for k, v in kw.items():
            setattr(self, k, v)

    def __repr__(self) -> str:
        return (
            f"PoseTick({self.tick}, heads={len(self.layout)}, changed={len(self.changed)}, "
            f"missing={len(self.missing)})"
        )


class StreamFrame:
    """One tick drawn by the server from the viewer's camera (``output="frames"``):
    ``tick`` and ``image`` (:class:`~crowdmorph.results.Image` bytes with ``width``,
    ``height`` and ``content_type``); ``format`` is ``png``, ``jpeg`` or ``rgba``;
    ``wire_bytes`` the bytes of the WebSocket message."""

    __slots__ = ("tick", "format", "image", "message", "wire_bytes")

    def __init__(self, message: TickFrame, wire_bytes: int = 0):
        self.message = message
        self.wire_bytes = wire_bytes
        self.tick: int = message.tick
        self.format: str = message.format
        img = Image(message.image)
        img.width = message.width
        img.height = message.height
        img.content_type = _CONTENT_TYPES.get(message.format, "application/octet-stream")
        img.server_timing = {}
        self.image = img

    @property
    def width(self) -> int:
        return self.image.width

    @property
    def height(self) -> int:
        return self.image.height

    def __repr__(self) -> str:
        return f"StreamFrame({self.tick}, {self.format}, {self.width}x{self.height})"


class Viewer:
    """A viewer of one session: an iterator of :class:`Tick` (or :class:`StreamFrame`).

    Made by :meth:`crowdmorph.Client.stream` (:func:`open_viewer`). Its state is the last
    message applied: ``tick``, ``layout``, ``positions``, ``normals`` and ``buffers`` (each a
    dict by head id, as in :class:`Tick`). :meth:`update` changes the camera or LOD from the
    next tick; :meth:`close` leaves (iteration then ends). A close by the server raises
    :class:`~crowdmorph.errors.StreamClosed` from the iteration, with its code and reason
    (``1008`` and why for a refused hello, ``1001 session deleted``...). ``ws`` is the
    ``websockets`` connection; ``timeout`` bounds each wait for a message (``None``: none).
    """

    def __init__(
        self,
        ws: Any,
        session: str,
        settings: Mapping[str, Any],
        backend: str,
        timeout: Optional[float] = None,
    ):
        self.ws = ws
        self.session = session
        #: The hello this viewer sent (JSON object).
        self.settings: Dict[str, Any] = dict(settings)
        self.backend = backend
        self.timeout = timeout
        self.tick = 0
        self.layout: List[SessionHead] = []
        self.positions: Dict[int, Any] = {}
        self.normals: Dict[int, Any] = {}
        self.buffers: Dict[int, Buffer] = {}
        #: For an ``output="weights"`` viewer: head id → its pose (``HeadPose``).
        self.poses: Dict[int, Any] = {}
        self._missing: set = set()
        self._closing = False
        #: How the stream ended (``None`` while open).
        self.closed: Optional[StreamClosed] = None

    # -- iteration ----------------------------------------------------------------------------

    def __iter__(self) -> Iterator[Union[Tick, StreamFrame]]:
        return self

    def __next__(self) -> Union[Tick, StreamFrame]:
        return self._next(self.timeout)

    def next(self, timeout: Optional[float] = None) -> Union[Tick, StreamFrame]:
        """The next tick, waiting at most ``timeout`` seconds (:class:`TimeoutError`, after
        which the stream is still usable; ``None``: the stream's ``timeout``)."""
        return self._next(self.timeout if timeout is None else timeout)

    def _next(self, timeout: Optional[float]) -> Union[Tick, StreamFrame]:
        if self._closing:
            raise StopIteration
        if self.closed is not None:
            raise self.closed
        closed = _websockets().exceptions.ConnectionClosed
        while True:
            try:
                data = self.ws.recv(timeout)
            except closed as e:
                self.closed = _stream_closed(e)
                raise self.closed from None
            if isinstance(data, str):
                continue  # The server sends only binary messages; text is for later versions.
            try:
                outer = decode_stream_message(data)
                if isinstance(outer, PackedMessage):
                    compression: Optional[str] = outer.encoding
                    msg = unpack_stream_message(data)
                else:
                    compression, msg = None, outer
            except (DecodeError, ImportError) as e:
                raise ProtocolError(101, "bad_stream_message", str(e)) from e
            if isinstance(msg, TickFrame):
                self.tick = msg.tick
                return StreamFrame(msg, len(data))
            if isinstance(msg, TickPoses):
                return self._apply_poses(msg, len(data))
            return self._apply(msg, len(data), compression)

    def _apply_poses(self, m: TickPoses, wire_bytes: int) -> "PoseTick":
        """Applies one poses message: every layout head gets its new pose, keeps its last
        one (``HEAD_UNCHANGED``) or has none (``HEAD_MISSING``). A message that does not fit
        what came before raises :class:`ProtocolError` and changes nothing."""

        def bad(why: str) -> ProtocolError:
            return ProtocolError(101, "bad_stream_message", f"tick {m.tick}: {why}")

        layout = self.layout if m.layout is None else m.layout
        ids, entries = m.heads.head_ids, m.heads.buffer_indices
        if len(ids) != len(layout):
            raise bad(f"{len(ids)} heads for a layout of {len(layout)}")
        prev = self.poses
        poses: Dict[int, Any] = {}
        changed: List[int] = []
        missing: List[int] = []
        for i, (hid, b) in enumerate(zip(ids, entries)):
            if hid != layout[i].head:
                raise bad(f"head {hid} where the layout has {layout[i].head}")
            if b == HEAD_MISSING:
                missing.append(hid)
            elif b == HEAD_UNCHANGED:
                if hid not in prev:
                    raise bad(f"head {hid} is unchanged but had no pose yet")
                poses[hid] = prev[hid]
            elif b >= len(m.poses):
                raise bad(f"head {hid} names pose {b} of {len(m.poses)}")
            else:
                poses[hid] = m.poses[b]
                changed.append(hid)
        self.layout = layout
        self.poses = poses
        self.tick = m.tick
        return PoseTick(
            tick=m.tick,
            layout=layout,
            layout_changed=m.layout is not None,
            poses=dict(poses),
            changed=changed,
            missing=missing,
            timings=m.timings,
            message=m,
            wire_bytes=wire_bytes,
        )

    def _apply(
        self,
        m: Union[TickVertices, TickDelta],
        wire_bytes: int = 0,
        compression: Optional[str] = None,
    ) -> Tick:
        """Applies one vertex message (as ``crowdmorph_proto::StreamState`` does): every layout
        head gets its new buffer, keeps its last one (``HEAD_UNCHANGED``) or has none
        (``HEAD_MISSING``); residual buffers decode against the head's last buffer. A message
        that does not fit what came before raises :class:`ProtocolError` and changes
        nothing."""

        def bad(why: str) -> ProtocolError:
            return ProtocolError(101, "bad_stream_message", f"tick {m.tick}: {why}")

        residual: Optional[List[bool]] = None
        if isinstance(m, TickDelta):
            if m.format != "q16":
                raise bad(f"a temporal message in {m.format}, not q16")
            if len(m.residual) != len(m.buffers):
                raise bad(f"{len(m.residual)} residual flags for {len(m.buffers)} buffers")
            residual = m.residual
        layout = self.layout if m.layout is None else m.layout
        ids = m.heads.head_ids
        entries = m.heads.buffer_indices
        if len(ids) != len(layout):
            raise bad(f"{len(ids)} heads for a layout of {len(layout)}")
        prev = self.buffers
        buffers: Dict[int, Buffer] = {}
        decoded: Dict[int, Buffer] = {}
        # Per residual buffer: (previous buffer, decoded) pairs, so that heads that name it
        # with the same previous buffer share one decoded buffer, as clones do.
        resolved: Dict[int, List[Any]] = {}
        missing_now = set(self._missing)
        changed: List[int] = []
        missing: List[int] = []
        from_residuals = 0
        for i, (hid, b) in enumerate(zip(ids, entries)):
            if hid != layout[i].head:
                raise bad(f"head {hid} where the layout has {layout[i].head}")
            if b == HEAD_UNCHANGED:
                if hid in prev:
                    buffers[hid] = prev[hid]
                elif hid in missing_now:
                    missing.append(hid)
                else:
                    raise bad(f"head {hid} is unchanged but had nothing yet")
                continue
            if b == HEAD_MISSING:
                missing_now.add(hid)
                missing.append(hid)
                continue
            if b >= len(m.buffers):
                raise bad(f"head {hid} names buffer {b} of {len(m.buffers)}")
            if residual is not None and residual[b]:
                before = prev.get(hid)
                if before is None:
                    raise bad(f"head {hid} has residuals but no earlier buffer")
                buf = None
                pairs = resolved.setdefault(b, [])
                for other, done in pairs:
                    if other is before or _same_values(other, before):
                        buf = done
                        break
                if buf is None:
                    try:
                        buf = _resolve(m.buffers[b], before, self.backend)
                    except ValueError as e:
                        raise bad(f"head {hid}: {e}") from e
                    pairs.append((before, buf))
                from_residuals += 1
            else:
                buf = decoded.get(b)
                if buf is None:
                    try:
                        buf = decoded[b] = Buffer(m.buffers[b], m.format, self.backend)
                    except ValueError as e:
                        raise ProtocolError(101, "bad_stream_message", str(e)) from e
            missing_now.discard(hid)
            buffers[hid] = buf
            changed.append(hid)
        # Everything decoded: the new state.
        self.layout = layout
        self._missing = missing_now & {h.head for h in layout}
        self.buffers = buffers
        self.positions = {hid: buf.positions for hid, buf in buffers.items()}
        self.normals = {
            hid: buf.normals for hid, buf in buffers.items() if buf.normals is not None
        }
        self.tick = m.tick
        return Tick(
            tick=m.tick,
            format=m.format,
            normals_included=m.normals,
            layout=self.layout,
            layout_changed=m.layout is not None,
            positions=dict(self.positions),
            normals=dict(self.normals),
            buffers=dict(self.buffers),
            changed=changed,
            missing=missing,
            timings=m.timings,
            message=m,
            wire_bytes=wire_bytes,
            compression=compression,
            keyframes=len(changed) - from_residuals,
            from_residuals=from_residuals,
        )

    # -- control ------------------------------------------------------------------------------

    def update(
        self,
        camera: Optional[Union[CameraSpec, Mapping[str, Any]]] = None,
        lod: Optional[Union[int, Sequence[Sequence[float]], Mapping[str, Any]]] = None,
    ) -> None:
        """Sends a ``ViewerUpdate``: a new camera and/or LOD, used from the next tick."""
        if camera is None and lod is None:
            raise ValueError("update needs a camera, a lod or both")
        msg: Dict[str, Any] = {}
        if camera is not None:
            msg["camera"] = camera_json(camera)
        if lod is not None:
            msg["lod"] = lod_json(lod)
        self._send(json.dumps(msg))

    def _send(self, text: str) -> None:
        if self.closed is not None:
            raise self.closed
        try:
            self.ws.send(text)
        except _websockets().exceptions.ConnectionClosed as e:
            self.closed = _stream_closed(e)
            raise self.closed from None

    def close(self, timeout: float = 5.0) -> None:
        """Leaves the session (close 1000), waiting at most ``timeout`` seconds for the
        server's answer; later iteration ends. ``closed`` then says how it ended: the
        server's answer (``1000``), or ``1006`` (``local``) when none came. Idempotent."""
        if self._closing:
            return
        self._closing = True
        if self.closed is not None:
            return  # The server closed it first; that is how it ended.
        ws = self.ws
        ws.close_timeout = timeout
        # Messages the viewer has not read are read and dropped meanwhile: websockets stops
        # reading while they wait (11 holds one, later releases max_queue frames), so that
        # they would hold back the server's close frame until the timeout.
        drain = threading.Thread(target=_drain, args=(ws,), daemon=True)
        drain.start()
        try:
            ws.close(1000)
        except OSError:
            pass
        drain.join(timeout)
        rcvd = ws.protocol.close_rcvd
        if rcvd is not None:
            self.closed = StreamClosed(int(rcvd.code), rcvd.reason)
        else:
            self.closed = StreamClosed(1006, "no close frame from the server", local=True)

    def __enter__(self) -> "Viewer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Viewer(session={self.session!r}, tick={self.tick}, heads={len(self.layout)})"


def _resolve(fb: Any, before: Buffer, backend: str) -> Buffer:
    """The buffer a head draws from the residual planes ``fb`` (a ``FrameBuffer`` of a
    ``TickDelta``) against ``before``, the head's previous buffer (q16): its positions, and
    its normals when ``fb`` has them, decode with ``q16r`` against the previous ones; the
    rest (rig, clip, frame, LOD, box) is ``fb``'s."""
    positions = _arrays.q16r_decode(fb.positions, before.wire.positions)
    normals = None
    if fb.normals is not None:
        if before.wire.normals is None:
            raise ValueError("residual normals but no earlier normals")
        normals = _arrays.q16r_decode(fb.normals, before.wire.normals)
    return Buffer(dataclasses.replace(fb, positions=positions, normals=normals), "q16", backend)


def _same_values(a: Buffer, b: Buffer) -> bool:
    """Whether two q16 buffers hold the same values (the same reference for residuals)."""
    wa, wb = a.wire, b.wire
    if wa.positions != wb.positions:
        return False
    if (wa.normals is None) != (wb.normals is None):
        return False
    return wa.normals is None or wa.normals == wb.normals


def camera_json(camera: Union[CameraSpec, Mapping[str, Any]]) -> Dict[str, Any]:
    """A camera as the hello's JSON (a :class:`CameraSpec` or a dict of its fields)."""
    if isinstance(camera, CameraSpec):
        return {k: v for k, v in as_dict(camera).items() if v is not None}
    if isinstance(camera, Mapping):
        return dict(camera)
    raise TypeError(f"camera is a CameraSpec or a dict, not {type(camera).__name__}")


def lod_json(lod: Union[int, Sequence[Sequence[float]], Mapping[str, Any]]) -> Any:
    """A LOD choice as JSON: a level for every head, ``[[metres, level], ...]`` (ascending
    metres) or ``{"by_distance": [...]}``."""
    if isinstance(lod, bool):
        raise TypeError("lod is a level, a by-distance table or a dict, not a bool")
    if isinstance(lod, int):
        return lod
    if isinstance(lod, Mapping):
        return dict(lod)
    return {"by_distance": [[float(m), int(level)] for m, level in lod]}


def hello(
    format: str = "q16",
    normals: bool = False,
    lod: Union[int, Sequence[Sequence[float]], Mapping[str, Any]] = 0,
    camera: Optional[Union[CameraSpec, Mapping[str, Any]]] = None,
    output: str = "vertices",
    image: Optional[Union[ImageOptions, Mapping[str, Any]]] = None,
    temporal: bool = False,
    keyframe_every: Optional[int] = None,
    compression: Optional[str] = None,
    tolerance: Optional[float] = None,
) -> Dict[str, Any]:
    """The ``ViewerHello`` JSON object a viewer sends first.

    ``tolerance`` (vertex buffers, with a camera): a head ``d`` metres from the eye may be off
    by ``tolerance × d`` of its rig's diagonal (near-clones; 0..=0.01 per metre), sent only
    when set.

    ``temporal``, ``keyframe_every`` and ``compression`` are sent only when set (an older
    server then sees the hello it knows). Which combinations a stream can give (``temporal``
    needs ``format="q16"`` and vertices; ``keyframe_every`` 1..=3600 needs ``temporal``) is
    the server's to say: it refuses the others with close 1008 and the reason.
    ``compression="zstd"`` needs the ``zstandard`` package (:class:`ImportError` saying what
    to install, before any connection)."""
    if output not in ("vertices", "frames", "weights"):
        raise ValueError(f"output must be 'vertices', 'frames' or 'weights', not {output!r}")
    if output == "weights":
        # Poses have no vertex format, normals or LOD: only compression goes with them.
        if temporal or keyframe_every is not None or normals or lod_json(lod) != 0:
            raise ValueError(
                "output 'weights' takes no temporal, keyframe_every, normals or lod: a pose "
                "is each head's whole pose"
            )
        weights: Dict[str, Any] = {"output": "weights"}
        if compression is not None:
            if compression not in MESSAGE_ENCODINGS:
                raise ValueError(
                    f"compression must be 'zstd', 'deflate' or None, not {compression!r}"
                )
            if compression == "zstd":
                _zstandard()
            weights["compression"] = compression
        return weights
    if format not in ("f32", "f16", "q16"):
        raise ValueError(f"format must be 'f32', 'f16' or 'q16', not {format!r}")
    msg: Dict[str, Any] = {
        "output": output,
        "format": format,
        "normals": bool(normals),
        "lod": lod_json(lod),
    }
    if camera is not None:
        msg["camera"] = camera_json(camera)
    if image is not None:
        if isinstance(image, ImageOptions):
            msg["image"] = as_dict(image)
        elif isinstance(image, Mapping):
            msg["image"] = dict(image)
        else:
            raise TypeError(f"image is ImageOptions or a dict, not {type(image).__name__}")
    if not isinstance(temporal, bool):
        raise TypeError(f"temporal is a bool, not {type(temporal).__name__}")
    if temporal:
        msg["temporal"] = True
    if keyframe_every is not None:
        if isinstance(keyframe_every, bool) or not isinstance(keyframe_every, int):
            raise TypeError(f"keyframe_every is an int, not {type(keyframe_every).__name__}")
        msg["keyframe_every"] = keyframe_every
    if compression is not None:
        if compression not in MESSAGE_ENCODINGS:
            raise ValueError(f"compression must be 'zstd', 'deflate' or None, not {compression!r}")
        if compression == "zstd":
            _zstandard()
        msg["compression"] = compression
    if tolerance is not None:
        if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)):
            raise TypeError(f"tolerance is a number, not {type(tolerance).__name__}")
        msg["tolerance"] = float(tolerance)
    return msg


def _websockets() -> Any:
    """The ``websockets`` package with its synchronous client, or an :class:`ImportError`
    that says what to install."""
    try:
        import websockets
        import websockets.exceptions
        import websockets.sync.client
    except ImportError as e:
        raise ImportError(
            f"session streams need the websockets package, version 11 or later: {INSTALL_HINT}",
            name="websockets",
        ) from e
    return websockets


def open_viewer(
    url: str,
    session: str,
    settings: Mapping[str, Any],
    backend: str,
    *,
    token: Optional[str] = None,
    user_agent: Optional[str] = None,
    timeout: Optional[float] = 30.0,
    max_message: Optional[int] = 1 << 31,
) -> Viewer:
    """Opens the WebSocket ``url`` (``ws://`` or ``wss://``, the stream of ``session``), sends
    the hello ``settings`` and returns its :class:`Viewer` (arrays of ``backend``).

    ``token`` is sent as ``Authorization: Bearer``; ``timeout`` bounds the handshake and each
    wait for a message; ``max_message`` is the largest message taken (``None``: any; a
    packed message counts at its compressed size). No WebSocket compression is offered (the
    hello's ``compression`` packs messages instead), proxies are not used (as by
    :class:`~crowdmorph.Client`'s HTTP calls), and no keepalive pings are sent (a viewer that
    stops reading would otherwise miss their answers and be closed). A hello asking for
    ``"compression": "zstd"`` without the ``zstandard`` package raises :class:`ImportError`
    before connecting.

    A refused handshake raises the :class:`~crowdmorph.errors.CrowdmorphError` of the server's
    JSON error body (a stream of an unknown session is a 404 ``unknown_session``); a broken
    one a :class:`~crowdmorph.errors.ProtocolError`; an unreachable server the socket's
    :class:`OSError`. Without ``websockets`` this raises :class:`ImportError`.
    """
    ws_mod = _websockets()
    if settings.get("compression") == "zstd":
        _zstandard()  # Before connecting: what to install, not a stream that cannot be read.
    client = ws_mod.sync.client
    exc = ws_mod.exceptions
    options: Dict[str, Any] = {
        "compression": None,
        "open_timeout": timeout,
        "close_timeout": 5.0,
        "max_size": max_message,
    }
    if token is not None:
        options["additional_headers"] = {"Authorization": f"Bearer {token}"}
    if user_agent is not None:
        options["user_agent_header"] = user_agent
    # Options that later websockets releases have: no proxy, no keepalive pings, at most a
    # frame or so read ahead (so that a slow viewer leaves the unread ticks to the server,
    # which then sends it the newest one instead), and the connection itself as the result
    # (`legacy`: what connect() returns without a `with` is to change).
    known = inspect.signature(client.connect).parameters
    optional = (("proxy", None), ("ping_interval", None), ("max_queue", 1), ("legacy", True))
    for name, value in optional:
        if name in known:
            options[name] = value
    try:
        ws = client.connect(url, **options)
    except exc.InvalidStatus as e:
        r = e.response
        retry_after, request_id = r.headers.get("Retry-After"), r.headers.get("x-request-id")
        raise error_from_response(r.status_code, r.body or b"", retry_after, request_id) from None
    except exc.InvalidHandshake as e:
        raise ProtocolError(101, "bad_handshake", str(e)) from e
    viewer = Viewer(ws, session, settings, backend, timeout)
    try:
        viewer._send(json.dumps(viewer.settings))
    except BaseException:
        ws.close()
        raise
    return viewer


def _stream_closed(e: Any) -> StreamClosed:
    """A ``websockets`` ``ConnectionClosed`` as :class:`StreamClosed`: the close frame of the
    side that closed first (``local`` when it was this one: ``1002`` the server broke the
    protocol, ``1007`` text that is not UTF-8, ``1009`` a message over ``max_message``), or
    ``1006`` when the connection ended without one."""
    rcvd, sent = e.rcvd, e.sent
    if sent is not None and (rcvd is None or e.rcvd_then_sent is False):
        return StreamClosed(int(sent.code), sent.reason, local=True)
    if rcvd is not None:
        return StreamClosed(int(rcvd.code), rcvd.reason)
    return StreamClosed(1006, "the connection ended without a close frame", local=True)


def _drain(ws: Any) -> None:
    """Reads and drops messages until the connection is closed."""
    try:
        while True:
            ws.recv()
    except Exception:
        pass

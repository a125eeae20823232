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
"""

from __future__ import annotations

import json
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Union

from .client import Buffer, Image
from .errors import ProtocolError, StreamClosed
from .messages import (
    HEAD_MISSING,
    HEAD_UNCHANGED,
    CameraSpec,
    ImageOptions,
    SessionHead,
    TickFrame,
    TickVertices,
    as_dict,
    decode_stream_message,
)
from .websocket import WebSocket
from .wire import DecodeError

__all__ = ["Viewer", "Tick", "StreamFrame", "hello", "lod_json", "camera_json"]

_CONTENT_TYPES = {"png": "image/png", "jpeg": "image/jpeg", "rgba": "application/octet-stream"}


class Tick:
    """One tick as a viewer draws it, after applying "unchanged" and "missing".

    - ``tick``: the session's tick number (from 1; later ticks may be skipped for a slow
      viewer), ``format`` and ``normals`` of the buffers, ``timings`` (microseconds).
    - ``layout``: the session's heads (:class:`~crowdmorph.messages.SessionHead`: rig, clip,
      offset, position, yaw, scale) in stream order; ``layout_changed`` is true when this
      message carried a new one (always for the first).
    - ``positions`` / ``normals``: head id → its current array (numpy ``(vertices, 3)``
      float32, or a flat ``array('f')``), for every head that has something to draw; clones
      share one array. ``normals`` is empty unless the viewer asked for them.
    - ``buffers``: head id → the :class:`~crowdmorph.client.Buffer` drawn (its ``rig``,
      ``clip``, ``frame`` played and ``lod``).
    - ``changed``: ids whose buffer this message brought; ``missing``: ids with nothing to
      draw (their rig or clip was deleted).
    - ``message``: the raw :class:`~crowdmorph.messages.TickVertices`.
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


class StreamFrame:
    """One tick drawn by the server from the viewer's camera (``output="frames"``):
    ``tick`` and ``image`` (:class:`~crowdmorph.client.Image` bytes with ``width``,
    ``height`` and ``content_type``); ``format`` is ``png``, ``jpeg`` or ``rgba``."""

    __slots__ = ("tick", "format", "image", "message")

    def __init__(self, message: TickFrame):
        self.message = message
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

    Its state is the last message applied: ``tick``, ``layout``, ``positions``, ``normals``
    and ``buffers`` (each a dict by head id, as in :class:`Tick`). :meth:`update` changes the
    camera or LOD from the next tick; :meth:`close` leaves (iteration then ends). A close by
    the server raises :class:`~crowdmorph.errors.StreamClosed` from the iteration, with its
    code and reason (``1008`` and why for a refused hello, ``1001 session deleted``...).
    """

    def __init__(self, ws: WebSocket, session: str, settings: Mapping[str, Any], backend: str):
        self.ws = ws
        self.session = session
        #: The hello this viewer sent (JSON object).
        self.settings: Dict[str, Any] = dict(settings)
        self.backend = backend
        self.tick = 0
        self.layout: List[SessionHead] = []
        self.positions: Dict[int, Any] = {}
        self.normals: Dict[int, Any] = {}
        self.buffers: Dict[int, Buffer] = {}
        self._missing: set = set()
        self._closing = False
        #: How the stream ended (``None`` while open).
        self.closed: Optional[StreamClosed] = None

    # -- iteration ----------------------------------------------------------------------------

    def __iter__(self) -> Iterator[Union[Tick, StreamFrame]]:
        return self

    def __next__(self) -> Union[Tick, StreamFrame]:
        if self._closing:
            raise StopIteration
        while True:
            try:
                data = self.ws.recv()
            except StreamClosed as e:
                self.closed = e
                raise
            if isinstance(data, str):
                continue  # The server sends only binary messages; text is for later versions.
            try:
                msg = decode_stream_message(data)
            except DecodeError as e:
                raise ProtocolError(101, "bad_stream_message", str(e)) from e
            if isinstance(msg, TickFrame):
                self.tick = msg.tick
                return StreamFrame(msg)
            return self._apply(msg)

    def next(self, timeout: Optional[float] = None) -> Union[Tick, StreamFrame]:
        """The next tick, waiting at most ``timeout`` seconds (:class:`TimeoutError`;
        ``None``: the client's timeout)."""
        if timeout is None:
            return next(self)
        before = self.ws.sock.gettimeout()
        self.ws.sock.settimeout(timeout)
        try:
            return next(self)
        finally:
            if self.ws.closed is None:
                self.ws.sock.settimeout(before)

    def _apply(self, m: TickVertices) -> Tick:
        layout_changed = m.layout is not None
        if m.layout is not None:
            self.layout = m.layout
            keep = {h.head for h in m.layout}
            for d in (self.positions, self.normals, self.buffers):
                for hid in [k for k in d if k not in keep]:
                    del d[hid]
            self._missing &= keep
        ids = m.heads.head_ids
        entries = m.heads.buffer_indices
        if len(ids) != len(self.layout):
            raise ProtocolError(
                101,
                "bad_stream_message",
                f"tick {m.tick}: {len(ids)} heads for a layout of {len(self.layout)}",
            )
        decoded: Dict[int, Buffer] = {}
        changed: List[int] = []
        missing: List[int] = []
        for i, (hid, b) in enumerate(zip(ids, entries)):
            if hid != self.layout[i].head:
                raise ProtocolError(
                    101,
                    "bad_stream_message",
                    f"tick {m.tick}: head {hid} where the layout has {self.layout[i].head}",
                )
            if b == HEAD_UNCHANGED:
                if hid not in self.buffers and hid not in self._missing:
                    raise ProtocolError(
                        101,
                        "bad_stream_message",
                        f"tick {m.tick}: head {hid} is unchanged but had nothing yet",
                    )
                if hid in self._missing:
                    missing.append(hid)
                continue
            if b == HEAD_MISSING:
                self.positions.pop(hid, None)
                self.normals.pop(hid, None)
                self.buffers.pop(hid, None)
                self._missing.add(hid)
                missing.append(hid)
                continue
            buf = decoded.get(b)
            if buf is None:
                if b >= len(m.buffers):
                    raise ProtocolError(
                        101,
                        "bad_stream_message",
                        f"tick {m.tick}: head {hid} names buffer {b} of {len(m.buffers)}",
                    )
                try:
                    buf = decoded[b] = Buffer(m.buffers[b], m.format, self.backend)
                except ValueError as e:
                    raise ProtocolError(101, "bad_stream_message", str(e)) from e
            self._missing.discard(hid)
            self.buffers[hid] = buf
            self.positions[hid] = buf.positions
            if buf.normals is not None:
                self.normals[hid] = buf.normals
            changed.append(hid)
        self.tick = m.tick
        return Tick(
            tick=m.tick,
            format=m.format,
            normals_included=m.normals,
            layout=self.layout,
            layout_changed=layout_changed,
            positions=dict(self.positions),
            normals=dict(self.normals),
            buffers=dict(self.buffers),
            changed=changed,
            missing=missing,
            timings=m.timings,
            message=m,
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
        self.ws.send_text(json.dumps(msg))

    def close(self, timeout: float = 5.0) -> None:
        """Leaves the session (close 1000); later iteration ends. Idempotent."""
        if self._closing:
            return
        self._closing = True
        self.closed = self.ws.close(1000, "", timeout=timeout)

    def __enter__(self) -> "Viewer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Viewer(session={self.session!r}, tick={self.tick}, heads={len(self.layout)})"


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
) -> Dict[str, Any]:
    """The ``ViewerHello`` JSON object a viewer sends first."""
    if output not in ("vertices", "frames"):
        raise ValueError(f"output must be 'vertices' or 'frames', not {output!r}")
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
    return msg

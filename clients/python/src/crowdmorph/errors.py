"""Typed errors, made from the server's JSON error bodies.

Every 4xx/5xx answer of a crowdmorph server has the body
``{"error":{"code":"unknown_rig","message":"no rig \\"x\\" (rigs: default-head)"}}``; codes are
stable, so programs branch on ``err.code`` (or on the subclass, which follows the HTTP status)
and show ``err.message`` to people. 503s carry ``Retry-After``: ``err.retry_after`` in seconds
(``None`` for ``render_unavailable``, which waiting does not cure).
"""

from __future__ import annotations

import json
from typing import Dict, Optional, Type

__all__ = [
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
    "error_from_response",
]


class CrowdmorphError(Exception):
    """An error answer of the server.

    Attributes: ``status`` (HTTP status), ``code`` (the stable snake_case code, e.g.
    ``unknown_rig``), ``message`` (what is wrong, naming the offending value), ``retry_after``
    (seconds from ``Retry-After``, or ``None``) and ``request_id`` (``x-request-id``, which the
    server logs).
    """

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        retry_after: Optional[float] = None,
        request_id: Optional[str] = None,
    ):
        super().__init__(f"{status} {code}: {message}")
        self.status = status
        self.code = code
        self.message = message
        self.retry_after = retry_after
        self.request_id = request_id


class BadRequest(CrowdmorphError):
    """400: the request is wrong (``frame_out_of_range``, ``invalid_rig``,
    ``malformed_bincode``...)."""


class Unauthorized(CrowdmorphError):
    """401: ``token_required`` or ``bad_token`` (the server has an admin token)."""


class Forbidden(CrowdmorphError):
    """403: ``builtin_rig``, ``builtin_clip`` (the embedded rig cannot be changed)."""


class NotFound(CrowdmorphError):
    """404: ``unknown_rig``, ``unknown_clip``, ``no_route``."""


class Conflict(CrowdmorphError):
    """409: ``rig_exists``, ``clip_exists``, ``rig_changed``, ``head_exists``, ``session_exists``."""


class TooLarge(CrowdmorphError):
    """413: over a size or memory limit (``upload_too_large``, ``rig_too_large``,
    ``response_too_large``, ``image_too_large``...); the message names the bytes and the flag."""


class UnsupportedMediaType(CrowdmorphError):
    """415: the body's Content-Type is not one the endpoint reads."""


class Unprocessable(CrowdmorphError):
    """422: ``cannot_prepare`` (the engine cannot hold the rig)."""


class ServerError(CrowdmorphError):
    """500 (``internal``: details only in the server log) or another unexpected status."""


class Unavailable(CrowdmorphError):
    """503: try again after ``retry_after`` seconds (``memory_full``, ``queue_full``,
    ``overloaded``, ``loading``, ``shutting_down``, ``render_busy``), or not at all
    (``render_unavailable``: the server has no adapter to draw with)."""


#: The 503s that mean "too much work now": back off for ``retry_after`` and retry.
OVERLOAD_CODES = frozenset({"queue_full", "overloaded", "memory_full", "render_busy"})


class Overloaded(Unavailable):
    """503 whose code is one of :data:`OVERLOAD_CODES`: the server sheds load; wait
    ``retry_after`` seconds."""


class DeadlineExceeded(CrowdmorphError):
    """504: ``deadline_exceeded`` (the request outlived the server's deadline)."""


class ProtocolError(CrowdmorphError):
    """The server's answer is not what the protocol says (a malformed body, an unexpected
    Content-Type). ``status`` is the HTTP status of the answer."""


class StreamClosed(Exception):
    """A session stream (WebSocket) ended: ``code`` and ``reason`` of its close frame.

    The server's codes (``proto/README.md``): ``1008`` with why a hello or update was refused
    (``"bad lod: distances must be finite and ascending"``), ``1009`` a viewer message over
    64 KiB, ``1013`` the session has all the viewers it takes or the server is stopping,
    ``1001`` the session was deleted (``"session deleted"``) or ended, ``1000`` the answer to
    this viewer's own close. ``local`` is true when this side ended the connection: ``1006``
    (it ended without a close frame, or no answer came to this side's close), ``1009`` a
    message over the stream's ``max_message``, or ``1002``/``1007`` when the server broke the
    WebSocket protocol.

    Not a :class:`CrowdmorphError`: its ``code`` is the WebSocket's number, not an HTTP
    error's string.
    """

    def __init__(self, code: int, reason: str = "", local: bool = False):
        super().__init__(f"stream closed with {code}" + (f": {reason}" if reason else ""))
        self.code = code
        self.reason = reason
        self.local = local


_BY_STATUS: Dict[int, Type[CrowdmorphError]] = {
    400: BadRequest,
    401: Unauthorized,
    403: Forbidden,
    404: NotFound,
    409: Conflict,
    413: TooLarge,
    415: UnsupportedMediaType,
    422: Unprocessable,
    500: ServerError,
    503: Unavailable,
    504: DeadlineExceeded,
}


def _retry_after(value: Optional[str]) -> Optional[float]:
    if value is None:
        return None
    try:
        return float(value)
    except ValueError:
        # An HTTP date is allowed by HTTP but crowdmorph sends seconds; keep the rest usable.
        return None


def error_from_response(
    status: int,
    body: bytes,
    retry_after: Optional[str] = None,
    request_id: Optional[str] = None,
) -> CrowdmorphError:
    """The exception for an error answer: its JSON body's code and message, its status's class.

    A body that is not crowdmorph's JSON (a proxy's HTML page, say) gives code
    ``http_<status>`` and the body's start as message, so nothing is lost.
    """
    code = f"http_{status}"
    message = body[:500].decode("utf-8", "replace").strip() or f"HTTP {status}"
    try:
        detail = json.loads(body)["error"]
        code = str(detail["code"])
        message = str(detail["message"])
    except (ValueError, KeyError, TypeError):
        pass
    cls = _BY_STATUS.get(status)
    if cls is None:
        cls = ServerError if status >= 500 else BadRequest
    if cls is Unavailable and code in OVERLOAD_CODES:
        cls = Overloaded
    return cls(status, code, message, _retry_after(retry_after), request_id)

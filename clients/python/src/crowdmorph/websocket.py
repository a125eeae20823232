"""A small WebSocket client (RFC 6455), standard library only, for session streams.

Session viewers (``GET /v1/sessions/{id}/stream``) need a WebSocket, and the package takes no
dependencies, so this module is one: the opening handshake (``Sec-WebSocket-Key`` and the
server's ``Sec-WebSocket-Accept``, checked), masked client frames, reassembly of fragmented
messages, pongs for pings, and the closing handshake. No extensions (compression) and no
subprotocols are offered, so the server sends plain frames.

A close, by the server or because the server broke the protocol, is raised as
:class:`~crowdmorph.errors.StreamClosed` with the code and reason: the server's own
(``1008`` and why the hello was refused, ``1001 session deleted``...), or the code this side
closed with (``1002`` protocol error, ``1007`` text that is not UTF-8, ``1009`` a message over
``max_message`` bytes, ``1006`` when the connection ended without a close frame).
"""

from __future__ import annotations

import base64
import hashlib
import http.client
import os
import socket
import ssl
import struct
import threading
from typing import Any, Mapping, Optional, Tuple, Union

from .errors import ProtocolError, StreamClosed, error_from_response

__all__ = ["WebSocket", "connect", "accept_key", "mask"]

#: The GUID RFC 6455 §1.3 appends to the key.
_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"

OP_CONTINUATION = 0x0
OP_TEXT = 0x1
OP_BINARY = 0x2
OP_CLOSE = 0x8
OP_PING = 0x9
OP_PONG = 0xA

#: Payloads up to this size are read whole before any byte is taken from the buffer, so that
#: a timeout while one arrives leaves the stream usable; larger ones are read in place.
_SMALL = 1 << 20

_U16 = struct.Struct(">H")
_U64 = struct.Struct(">Q")


def accept_key(key: str) -> str:
    """The ``Sec-WebSocket-Accept`` a server must answer ``Sec-WebSocket-Key: key`` with."""
    return base64.b64encode(hashlib.sha1(key.encode("ascii") + _GUID).digest()).decode("ascii")


def mask(data: Any, key: bytes) -> bytes:
    """``data`` XOR the 4-byte ``key`` repeated (RFC 6455 §5.3); masking twice unmasks.

    Done as one big-integer XOR: a Python loop over the bytes would cost a microsecond each.
    """
    n = len(data)
    if n == 0:
        return b""
    stream = (key * (n // 4 + 1))[:n]
    return (int.from_bytes(data, "little") ^ int.from_bytes(stream, "little")).to_bytes(
        n, "little"
    )


def frame_header(opcode: int, n: int, fin: bool = True, masked: bool = True) -> bytearray:
    """The first bytes of a frame: FIN and opcode, the mask bit and the payload length."""
    head = bytearray([(0x80 if fin else 0) | opcode])
    bit = 0x80 if masked else 0
    if n < 126:
        head.append(bit | n)
    elif n < 1 << 16:
        head.append(bit | 126)
        head += _U16.pack(n)
    else:
        head.append(bit | 127)
        head += _U64.pack(n)
    return head


class WebSocket:
    """An open WebSocket connection (client side). Made by :func:`connect`.

    :meth:`recv` returns the next data message (``str`` for text, ``bytes`` or ``bytearray``
    for binary), answering pings on the way; :meth:`send_text`, :meth:`send_binary` and
    :meth:`ping` send; :meth:`close` runs the closing handshake. Sends may come from another
    thread than the one receiving (a lock keeps frames whole); receives must not.

    A timeout (``sock.settimeout``) that expires in :meth:`recv` raises :class:`TimeoutError`;
    the connection stays usable unless the timeout hit in the middle of a payload over 1 MiB,
    in which case it is closed (the next call raises :class:`StreamClosed` 1006).
    """

    def __init__(self, sock: socket.socket, buffered: bytes = b"", max_message: int = 1 << 31):
        self.sock = sock
        self.max_message = max_message
        self._buf = bytearray(buffered)
        self._send_lock = threading.Lock()
        # A fragmented message in progress: its opcode and the payloads so far.
        self._op: Optional[int] = None
        self._parts: list = []
        self._size = 0
        self._close_sent = False
        #: The close that ended the connection (``None`` while open).
        self.closed: Optional[StreamClosed] = None

    # -- sending ------------------------------------------------------------------------------

    def _send_frame(self, opcode: int, payload: Any, fin: bool = True) -> None:
        key = os.urandom(4)
        head = frame_header(opcode, len(payload), fin)
        head += key
        data = bytes(head) + mask(payload, key)
        with self._send_lock:
            self.sock.sendall(data)

    def _check_open(self) -> None:
        if self.closed is not None:
            raise self.closed
        if self._close_sent:
            raise StreamClosed(1000, "closed by this side", local=True)

    def send_text(self, text: str) -> None:
        """Sends a text message (one frame)."""
        self._check_open()
        self._send_frame(OP_TEXT, text.encode("utf-8"))

    def send_binary(self, data: Any) -> None:
        """Sends a binary message (one frame)."""
        self._check_open()
        self._send_frame(OP_BINARY, data)

    def ping(self, data: bytes = b"") -> None:
        """Sends a ping (at most 125 bytes); the server's pong is read and dropped by recv."""
        if len(data) > 125:
            raise ValueError("a ping carries at most 125 bytes")
        self._check_open()
        self._send_frame(OP_PING, data)

    # -- receiving ----------------------------------------------------------------------------

    def _fill(self, n: int) -> None:
        """Reads until the buffer holds ``n`` bytes; the end of the connection raises 1006."""
        while len(self._buf) < n:
            chunk = self.sock.recv(max(65536, n - len(self._buf)))
            if not chunk:
                raise self._drop(1006, "the connection ended without a close frame")
            self._buf += chunk

    def _drop(self, code: int, reason: str) -> StreamClosed:
        """Closes the socket without a handshake and returns the error to raise."""
        self.closed = StreamClosed(code, reason, local=True)
        try:
            self.sock.close()
        except OSError:
            pass
        return self.closed

    def _fail(self, code: int, reason: str) -> StreamClosed:
        """Fails the connection (RFC 6455 §7.1.7): a close frame with ``code``, then drop."""
        if not self._close_sent:
            try:
                self._send_close(code, reason)
            except OSError:
                pass
        return self._drop(code, f"{reason} (closed by this client)")

    def _read_frame(self) -> Tuple[bool, int, Any]:
        """One frame: FIN, opcode and the unmasked payload."""
        self._fill(2)
        b0, b1 = self._buf[0], self._buf[1]
        n = b1 & 0x7F
        at = 2
        if n == 126:
            at = 4
        elif n == 127:
            at = 10
        self._fill(at)
        if n == 126:
            n = _U16.unpack_from(self._buf, 2)[0]
        elif n == 127:
            n = _U64.unpack_from(self._buf, 2)[0]
        fin, opcode = bool(b0 & 0x80), b0 & 0x0F
        if b0 & 0x70:
            raise self._fail(1002, "a frame has reserved bits set (no extension was agreed)")
        if b1 & 0x80:
            raise self._fail(1002, "the server masked a frame")
        if opcode >= 8 and (n > 125 or not fin):
            raise self._fail(1002, "a control frame is fragmented or over 125 bytes")
        if self._size + n > self.max_message:
            raise self._fail(1009, f"a message over {self.max_message} bytes")
        if n <= _SMALL:
            self._fill(at + n)
            payload = bytes(self._buf[at : at + n])
            del self._buf[:at + n]
            return fin, opcode, payload
        # A large payload: read straight into its own buffer (one copy, not three).
        del self._buf[:at]
        out = bytearray(n)
        have = min(len(self._buf), n)
        out[:have] = self._buf[:have]
        del self._buf[:have]
        view = memoryview(out)
        try:
            while have < n:
                got = self.sock.recv_into(view[have:], n - have)
                if got == 0:
                    raise self._drop(1006, "the connection ended without a close frame")
                have += got
        except socket.timeout:
            self._drop(1006, "a timeout in the middle of a frame")
            raise
        return fin, opcode, out

    def recv(self) -> Union[str, bytes, bytearray]:
        """The next data message. Pings are answered and pongs dropped on the way; a close
        frame is answered and raised as :class:`StreamClosed` with the server's code and
        reason (after this side's :meth:`close`, too, once the server's answer arrives)."""
        if self.closed is not None:
            raise self.closed
        while True:
            fin, opcode, payload = self._read_frame()
            if opcode == OP_CLOSE:
                raise self._on_close(payload)
            if opcode == OP_PING:
                if not self._close_sent:
                    self._send_frame(OP_PONG, payload)
                continue
            if opcode == OP_PONG:
                continue
            if opcode == OP_CONTINUATION:
                if self._op is None:
                    raise self._fail(1002, "a continuation frame with no message to continue")
            elif opcode in (OP_TEXT, OP_BINARY):
                if self._op is not None:
                    raise self._fail(1002, "a new message inside a fragmented one")
                self._op = opcode
            else:
                raise self._fail(1002, f"reserved opcode 0x{opcode:x}")
            self._parts.append(payload)
            self._size += len(payload)
            if not fin:
                continue
            op, parts = self._op, self._parts
            self._op, self._parts, self._size = None, [], 0
            data = parts[0] if len(parts) == 1 else b"".join(parts)
            if op == OP_TEXT:
                try:
                    return bytes(data).decode("utf-8")
                except UnicodeDecodeError:
                    raise self._fail(1007, "a text message that is not UTF-8") from None
            return data

    def _on_close(self, payload: bytes) -> StreamClosed:
        if len(payload) == 1:
            raise self._fail(1002, "a close frame with a 1-byte body")
        if payload:
            code = _U16.unpack_from(payload)[0]
            try:
                reason = payload[2:].decode("utf-8")
            except UnicodeDecodeError:
                raise self._fail(1007, "a close reason that is not UTF-8") from None
        else:
            code, reason = 1005, ""  # RFC 6455 §7.1.5: no status code was present.
        if not self._close_sent:
            # Echo the code (§5.5.1), then the server closes the TCP connection.
            try:
                self._send_close(1000 if code == 1005 else code, "")
            except OSError:
                pass
        self.closed = StreamClosed(code, reason)
        try:
            self.sock.close()
        except OSError:
            pass
        return self.closed

    # -- closing ------------------------------------------------------------------------------

    def _send_close(self, code: int, reason: str) -> None:
        self._close_sent = True
        body = _U16.pack(code) + reason.encode("utf-8")[:123]
        self._send_frame(OP_CLOSE, body)

    def close(self, code: int = 1000, reason: str = "", timeout: float = 5.0) -> StreamClosed:
        """Closes the connection: sends a close frame, reads (and drops) what the server still
        sends until its close frame, then closes the socket. Returns how it ended: the
        server's answer (normally ``1000``), or 1006 when none came within ``timeout``."""
        if self.closed is not None:
            return self.closed
        try:
            if not self._close_sent:
                self._send_close(code, reason)
            self.sock.settimeout(timeout)
            while True:
                self.recv()
        except StreamClosed as e:
            return e
        except (OSError, ProtocolError):
            # A timeout or a reset: the socket is closed below all the same.
            return self._drop(1006, "no close frame from the server")
        finally:
            if self.closed is None:
                self._drop(1006, "no close frame from the server")

    def __enter__(self) -> "WebSocket":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def connect(
    host: str,
    port: int,
    path: str,
    *,
    tls: bool = False,
    headers: Optional[Mapping[str, str]] = None,
    timeout: Optional[float] = 30.0,
    max_message: int = 1 << 31,
) -> WebSocket:
    """Opens a WebSocket to ``host:port`` at ``path`` (with its query), over TLS when ``tls``.

    An answer other than ``101 Switching Protocols`` raises the
    :class:`~crowdmorph.errors.CrowdmorphError` of its JSON error body (a stream of an unknown
    session is a 404 ``unknown_session``); a 101 without the right ``Sec-WebSocket-Accept`` is a
    :class:`~crowdmorph.errors.ProtocolError`.
    """
    sock = socket.create_connection((host, port), timeout=timeout)
    try:
        if tls:
            sock = ssl.create_default_context().wrap_socket(sock, server_hostname=host)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        key = base64.b64encode(os.urandom(16)).decode("ascii")
        hostport = host if port in (None, 443 if tls else 80) else f"{host}:{port}"
        if ":" in host and not host.startswith("["):
            hostport = f"[{host}]:{port}"
        lines = [
            f"GET {path} HTTP/1.1",
            f"Host: {hostport}",
            "Upgrade: websocket",
            "Connection: Upgrade",
            f"Sec-WebSocket-Key: {key}",
            "Sec-WebSocket-Version: 13",
        ]
        lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
        sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1"))
        status, reason, head, rest = _read_head(sock)
        if status != 101:
            body = _read_body(sock, head, rest)
            raise error_from_response(
                status, body, head.get("retry-after"), head.get("x-request-id")
            )
        if (
            head.get("upgrade", "").lower() != "websocket"
            or "upgrade" not in head.get("connection", "").lower()
        ):
            raise _bad_handshake("the 101 answer does not upgrade to websocket")
        if head.get("sec-websocket-accept") != accept_key(key):
            raise _bad_handshake("wrong Sec-WebSocket-Accept in the 101 answer")
        if head.get("sec-websocket-extensions"):
            raise _bad_handshake("the server chose an extension although none was offered")
        return WebSocket(sock, rest, max_message)
    except BaseException:
        sock.close()
        raise


def _bad_handshake(message: str) -> ProtocolError:
    return ProtocolError(101, "bad_handshake", message)


def _read_head(sock: socket.socket) -> Tuple[int, str, http.client.HTTPMessage, bytes]:
    """The status line and headers of the handshake's answer, and the bytes after them."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        if len(buf) > 65536:
            raise ProtocolError(0, "bad_handshake", "the answer's headers exceed 64 KiB")
        chunk = sock.recv(4096)
        if not chunk:
            raise ConnectionError("the server closed the connection during the handshake")
        buf += chunk
    head, _, rest = buf.partition(b"\r\n\r\n")
    status_line, _, fields = head.partition(b"\r\n")
    parts = status_line.decode("latin-1").split(" ", 2)
    try:
        status = int(parts[1])
    except (IndexError, ValueError):
        raise ProtocolError(0, "bad_handshake", f"bad status line {status_line[:80]!r}") from None
    msg = http.client.parse_headers(_Lines(fields + b"\r\n\r\n"))
    return status, parts[2] if len(parts) > 2 else "", msg, rest


class _Lines:
    """Just enough of a binary file for :func:`http.client.parse_headers`."""

    def __init__(self, data: bytes):
        self._lines = data.splitlines(keepends=True)

    def readline(self, limit: int = -1) -> bytes:
        return self._lines.pop(0) if self._lines else b""


def _read_body(sock: socket.socket, head: http.client.HTTPMessage, rest: bytes) -> bytes:
    """The body of a refused handshake (an error's JSON), up to 64 KiB."""
    try:
        want = int(head.get("content-length", "-1"))
    except ValueError:
        want = -1
    chunked = "chunked" in head.get("transfer-encoding", "").lower()
    body = rest
    try:
        while len(body) < 65536:
            if want >= 0 and len(body) >= want:
                break
            if chunked and body.endswith(b"0\r\n\r\n"):
                break
            chunk = sock.recv(65536)
            if not chunk:
                break
            body += chunk
    except OSError:
        pass
    if chunked:
        return _unchunk(body)
    return body[:want] if want >= 0 else body


def _unchunk(data: bytes) -> bytes:
    out = b""
    while data:
        size_line, _, data = data.partition(b"\r\n")
        try:
            n = int(size_line.split(b";")[0], 16)
        except ValueError:
            break
        if n == 0:
            break
        out += data[:n]
        data = data[n + 2 :]
    return out

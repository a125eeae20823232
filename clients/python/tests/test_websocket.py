"""The hand-written WebSocket client (``crowdmorph.websocket``) against a scripted server.

The crowdmorph server never fragments, never pings and never breaks the protocol, so those
paths are driven here by a small server on a loopback socket that plays a script: it checks
the handshake and the client's frames byte by byte (masking) and sends frames the client must
reassemble, answer or refuse. The RFC 6455 worked examples pin the key and mask arithmetic.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import threading
from typing import Callable, List, Optional, Tuple

import pytest

import crowdmorph
from crowdmorph import websocket as ws_mod
from crowdmorph.websocket import OP_BINARY, OP_CLOSE, OP_CONTINUATION, OP_PING, OP_PONG, OP_TEXT


def test_the_accept_key_and_masking_match_rfc_6455s_examples():
    # RFC 6455 §1.3: the sample nonce and its accept value.
    assert ws_mod.accept_key("dGhlIHNhbXBsZSBub25jZQ==") == "s3pPLMBiTxaQ9kYGzzhZRbK+xOo="
    # RFC 6455 §5.7: a masked text frame "Hello".
    frame = bytes([0x81, 0x85, 0x37, 0xFA, 0x21, 0x3D, 0x7F, 0x9F, 0x4D, 0x51, 0x58])
    key = frame[2:6]
    assert ws_mod.mask(frame[6:], key) == b"Hello"
    assert bytes(ws_mod.frame_header(OP_TEXT, 5)) == frame[:2]


@pytest.mark.parametrize("n", [0, 1, 3, 4, 5, 125, 4097])
def test_masking_is_the_byte_wise_xor(n):
    data = os.urandom(n)
    key = os.urandom(4)
    want = bytes(b ^ key[i % 4] for i, b in enumerate(data))
    assert ws_mod.mask(data, key) == want
    assert ws_mod.mask(want, key) == data


@pytest.mark.parametrize("n, length_bytes", [(125, 2), (126, 4), (65535, 4), (65536, 10)])
def test_frame_headers_use_the_shortest_length_form(n, length_bytes):
    head = ws_mod.frame_header(OP_BINARY, n, masked=False)
    assert len(head) == length_bytes and head[0] == 0x82


# ---------------------------------------------------------------------------------------------
# A scripted server.


class Peer:
    """The server's end of one connection: raw frames in and out."""

    def __init__(self, conn: socket.socket, request: bytes):
        self.conn = conn
        self.request = request
        self.buf = b""

    def _exact(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.conn.recv(65536)
            if not chunk:
                raise EOFError("the client closed the connection")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def send_frame(self, opcode: int, payload: bytes = b"", fin: bool = True, **kw) -> None:
        head = ws_mod.frame_header(opcode, len(payload), fin, masked=kw.get("masked", False))
        if kw.get("rsv"):
            head[0] |= 0x40
        if kw.get("masked"):
            key = b"\x01\x02\x03\x04"
            self.conn.sendall(bytes(head) + key + ws_mod.mask(payload, key))
        else:
            self.conn.sendall(bytes(head) + payload)

    def send_close(self, code: int, reason: str = "") -> None:
        self.send_frame(OP_CLOSE, struct.pack(">H", code) + reason.encode())

    def read_frame(self) -> Tuple[bool, int, bytes]:
        """A client frame, unmasked; asserts that it was masked."""
        b0, b1 = self._exact(2)
        assert b1 & 0x80, "client frames are masked"
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        key = self._exact(4)
        return bool(b0 & 0x80), b0 & 0x0F, ws_mod.mask(self._exact(n), key)


class Scripted:
    """A one-connection WebSocket server on 127.0.0.1 that runs ``script(peer)`` after the
    handshake; ``answer`` replaces the 101 (for refused handshakes)."""

    def __init__(
        self,
        script: Callable[[Peer], None],
        answer: Optional[Callable[[str], bytes]] = None,
    ):
        self.listener = socket.socket()
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(1)
        self.port = self.listener.getsockname()[1]
        self.script = script
        self.answer = answer
        self.error: Optional[BaseException] = None
        self.peer: Optional[Peer] = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            conn, _ = self.listener.accept()
            conn.settimeout(10)
            with conn:
                request = b""
                while b"\r\n\r\n" not in request:
                    request += conn.recv(4096)
                head, _, rest = request.partition(b"\r\n\r\n")
                key = ""
                for line in head.decode().split("\r\n")[1:]:
                    k, _, v = line.partition(":")
                    if k.strip().lower() == "sec-websocket-key":
                        key = v.strip()
                if self.answer is not None:
                    conn.sendall(self.answer(key))
                    return
                conn.sendall(
                    (
                        "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n"
                        "Connection: Upgrade\r\n"
                        f"Sec-WebSocket-Accept: {ws_mod.accept_key(key)}\r\n\r\n"
                    ).encode()
                )
                self.peer = Peer(conn, head)
                self.peer.buf = rest
                self.script(self.peer)
        except BaseException as e:  # reported by join()
            self.error = e
        finally:
            self.listener.close()

    def connect(self, **kw) -> ws_mod.WebSocket:
        return ws_mod.connect("127.0.0.1", self.port, "/v1/sessions/s1/stream", timeout=10, **kw)

    def join(self) -> None:
        self.thread.join(10)
        assert not self.thread.is_alive(), "the scripted server did not finish"
        if self.error is not None:
            raise self.error


def test_the_handshake_sends_a_fresh_key_and_the_hello_arrives_masked():
    got: List[Tuple[bool, int, bytes]] = []

    def script(peer: Peer) -> None:
        got.append(peer.read_frame())
        got.append(peer.read_frame())
        got.append(peer.read_frame())

    server = Scripted(script)
    ws = server.connect(headers={"Authorization": "Bearer t"})
    ws.send_text('{"format": "q16"}')
    ws.send_binary(b"\x00" * 300)
    ws.send_binary(os.urandom(70_000))
    server.join()
    request = server.peer.request.decode()
    lines = request.split("\r\n")
    assert lines[0] == "GET /v1/sessions/s1/stream HTTP/1.1"
    fields = {k.lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
    assert fields["upgrade"] == "websocket" and fields["connection"] == "Upgrade"
    assert fields["sec-websocket-version"] == "13"
    assert len(base64.b64decode(fields["sec-websocket-key"])) == 16
    assert fields["authorization"] == "Bearer t"
    assert got[0] == (True, OP_TEXT, b'{"format": "q16"}')
    assert got[1] == (True, OP_BINARY, b"\x00" * 300)
    assert got[2][1] == OP_BINARY and len(got[2][2]) == 70_000


def test_a_wrong_accept_key_is_refused():
    def answer(key: str) -> bytes:
        return (
            "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Accept: {ws_mod.accept_key(key + 'x')}\r\n\r\n"
        ).encode()

    server = Scripted(lambda p: None, answer)
    with pytest.raises(crowdmorph.ProtocolError, match="Sec-WebSocket-Accept"):
        server.connect()
    server.join()


def test_a_refused_handshake_raises_the_servers_json_error():
    body = json.dumps(
        {"error": {"code": "unknown_session", "message": 'no session "s1"'}}
    ).encode()

    def answer(key: str) -> bytes:
        return (
            b"HTTP/1.1 404 Not Found\r\ncontent-type: application/json\r\n"
            b"x-request-id: r-1\r\ncontent-length: " + str(len(body)).encode() + b"\r\n\r\n" + body
        )

    server = Scripted(lambda p: None, answer)
    with pytest.raises(crowdmorph.NotFound) as e:
        server.connect()
    assert (e.value.code, e.value.message, e.value.request_id) == (
        "unknown_session",
        'no session "s1"',
        "r-1",
    )
    server.join()


def test_fragments_are_reassembled_and_pings_answered_in_between():
    pongs: List[bytes] = []
    big = os.urandom(3 << 20)  # over 1 MiB: read in place, not through the buffer

    def script(peer: Peer) -> None:
        peer.send_frame(OP_TEXT, "héllo, ".encode(), fin=False)
        peer.send_frame(OP_PING, b"are you there")
        peer.send_frame(OP_CONTINUATION, "wör".encode(), fin=False)
        peer.send_frame(OP_PONG, b"unasked")  # an unsolicited pong is ignored
        peer.send_frame(OP_CONTINUATION, "ld".encode(), fin=True)
        fin, op, payload = peer.read_frame()
        assert (fin, op) == (True, OP_PONG)
        pongs.append(payload)
        peer.send_frame(OP_BINARY, big[:1000], fin=False)
        peer.send_frame(OP_CONTINUATION, big[1000:], fin=True)
        peer.send_frame(OP_BINARY, b"")
        peer.send_close(1000)
        assert peer.read_frame()[1] == OP_CLOSE

    server = Scripted(script)
    ws = server.connect()
    assert ws.recv() == "héllo, wörld"
    assert bytes(ws.recv()) == big
    assert ws.recv() == b""
    with pytest.raises(crowdmorph.StreamClosed):
        ws.recv()
    server.join()
    assert pongs == [b"are you there"]


def test_a_close_frame_is_raised_with_its_code_and_reason_and_echoed():
    echoed: List[Tuple[bool, int, bytes]] = []

    def script(peer: Peer) -> None:
        peer.send_frame(OP_BINARY, b"tick")
        peer.send_close(1008, "bad hello at format: unknown variant `f64`")
        echoed.append(peer.read_frame())

    server = Scripted(script)
    ws = server.connect()
    assert ws.recv() == b"tick"
    with pytest.raises(crowdmorph.StreamClosed) as e:
        ws.recv()
    assert (e.value.code, e.value.reason, e.value.local) == (
        1008,
        "bad hello at format: unknown variant `f64`",
        False,
    )
    # Later calls raise the same close; sends are refused.
    with pytest.raises(crowdmorph.StreamClosed) as again:
        ws.recv()
    assert again.value is e.value
    with pytest.raises(crowdmorph.StreamClosed):
        ws.send_text("{}")
    server.join()
    assert echoed == [(True, OP_CLOSE, struct.pack(">H", 1008))]


def test_a_close_without_a_code_reads_as_1005():
    server = Scripted(lambda peer: (peer.send_frame(OP_CLOSE, b""), peer.read_frame()))
    ws = server.connect()
    with pytest.raises(crowdmorph.StreamClosed) as e:
        ws.recv()
    assert (e.value.code, e.value.reason) == (1005, "")
    server.join()


def test_a_connection_that_ends_without_a_close_frame_is_1006():
    server = Scripted(lambda peer: peer.send_frame(OP_BINARY, b"x" * 10, fin=False))
    ws = server.connect()
    with pytest.raises(crowdmorph.StreamClosed) as e:
        ws.recv()
    assert e.value.code == 1006 and e.value.local
    server.join()


def test_our_close_waits_for_the_servers_answer_and_drops_what_comes_before():
    seen: List[Tuple[bool, int, bytes]] = []

    def script(peer: Peer) -> None:
        seen.append(peer.read_frame())
        peer.send_frame(OP_BINARY, b"a late tick")
        peer.send_close(1000)

    server = Scripted(script)
    ws = server.connect()
    ended = ws.close(1000, "bye")
    assert (ended.code, ended.local) == (1000, False)
    assert ws.close() is ended  # idempotent
    server.join()
    assert seen == [(True, OP_CLOSE, struct.pack(">H", 1000) + b"bye")]


@pytest.mark.parametrize(
    "send, code, why",
    [
        (lambda p: p.send_frame(OP_BINARY, b"x", masked=True), 1002, "masked"),
        (lambda p: p.send_frame(OP_BINARY, b"x", rsv=True), 1002, "reserved bits"),
        (lambda p: p.send_frame(OP_CONTINUATION, b"x"), 1002, "continuation"),
        (lambda p: p.send_frame(0x3, b"x"), 1002, "reserved opcode"),
        (lambda p: p.send_frame(OP_PING, b"x" * 126), 1002, "control frame"),
        (lambda p: p.send_frame(OP_PING, b"x", fin=False), 1002, "control frame"),
        (
            lambda p: (p.send_frame(OP_TEXT, b"a", fin=False), p.send_frame(OP_TEXT, b"b")),
            1002,
            "inside a fragmented",
        ),
        (lambda p: p.send_frame(OP_TEXT, b"\xff\xfe"), 1007, "not UTF-8"),
        (lambda p: p.send_frame(OP_BINARY, b"x" * 2000), 1009, "over 1000 bytes"),
        (lambda p: p.send_frame(OP_CLOSE, b"\x03"), 1002, "1-byte"),
    ],
)
def test_a_server_that_breaks_the_protocol_is_closed_with_the_rfcs_code(send, code, why):
    closes: List[bytes] = []

    def script(peer: Peer) -> None:
        send(peer)
        fin, op, payload = peer.read_frame()
        assert op == OP_CLOSE
        closes.append(payload)

    server = Scripted(script)
    ws = server.connect(max_message=1000)
    with pytest.raises(crowdmorph.StreamClosed) as e:
        ws.recv()
    assert e.value.code == code and e.value.local
    assert why in e.value.reason
    server.join()
    assert struct.unpack(">H", closes[0][:2])[0] == code


def test_a_timeout_between_messages_leaves_the_stream_usable():
    go = threading.Event()

    def script(peer: Peer) -> None:
        go.wait(10)
        peer.send_frame(OP_BINARY, b"late")
        peer.send_close(1000)
        peer.read_frame()

    server = Scripted(script)
    ws = server.connect()
    ws.sock.settimeout(0.2)
    with pytest.raises(socket.timeout):
        ws.recv()
    go.set()
    ws.sock.settimeout(10)
    assert ws.recv() == b"late"
    with pytest.raises(crowdmorph.StreamClosed):
        ws.recv()
    server.join()

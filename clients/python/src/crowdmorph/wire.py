"""The bincode encoding of the crowdmorph v1 protocol, written from ``proto/README.md``.

bincode 2 with its standard configuration: little-endian, variable-length integers, a
message's fields concatenated in order with no names, tags or padding, and nothing after the
last field. This module holds the primitive codecs (:class:`Reader`, :class:`Writer`) and small
composable type descriptions (``U32``, ``Opt(STR)``, ``Vec(...)``, ``Msg(cls)``...) that the
message classes in :mod:`crowdmorph.messages` are declared with, so that a new message (the
session messages, for one) is a list of fields, not new parsing code.

Payloads (``Blob``) are returned as :class:`memoryview` slices of the response body: a crowd
frame of a hundred unique heads is tens of megabytes, and slicing a ``bytes`` would copy it.
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any, Callable, List, Sequence

__all__ = [
    "DecodeError",
    "Reader",
    "Writer",
    "encode",
    "decode",
    "encode_as",
    "decode_as",
    "Tagged",
]

_F32 = struct.Struct("<f")
_F64 = struct.Struct("<d")
_F32X3 = struct.Struct("<3f")
_F32X4 = struct.Struct("<4f")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
# A varint's marker and its 2, 4 or 8 bytes, packed in one call.
VAR16 = struct.Struct("<BH")
VAR32 = struct.Struct("<BI")
VAR64 = struct.Struct("<BQ")

_U32_MAX = 0xFFFF_FFFF
_U64_MAX = 0xFFFF_FFFF_FFFF_FFFF


class DecodeError(ValueError):
    """Bytes that are not a valid encoding of the expected message.

    ``offset`` is where in the body the problem was found, so that a report can point at it.
    """

    def __init__(self, message: str, offset: int = -1):
        super().__init__(
            f"malformed bincode at byte {offset}: {message}" if offset >= 0 else message
        )
        self.offset = offset


class Reader:
    """Reads bincode values from a buffer, front to back, without copying payloads."""

    __slots__ = ("buf", "pos")

    def __init__(self, data: Any):
        # A memoryview so that byte strings are slices of the body, not copies.
        self.buf = memoryview(data).cast("B")
        self.pos = 0

    def _take(self, n: int) -> memoryview:
        end = self.pos + n
        if n < 0 or end > len(self.buf):
            raise DecodeError(f"needs {n} bytes, {len(self.buf) - self.pos} left", self.pos)
        view = self.buf[self.pos : end]
        self.pos = end
        return view

    def u8(self) -> int:
        if self.pos >= len(self.buf):
            raise DecodeError("needs 1 byte, 0 left", self.pos)
        b = self.buf[self.pos]
        self.pos += 1
        return b

    def bool(self) -> bool:
        at = self.pos
        b = self.u8()
        if b > 1:
            raise DecodeError(f"bool byte is {b}, not 0 or 1", at)
        return b == 1

    def varint(self) -> int:
        """A ``u64`` varint: one byte below 251, else a marker and 2, 4 or 8 bytes LE."""
        at = self.pos
        b = self.u8()
        if b < 251:
            return b
        if b == 251:
            return _U16.unpack(self._take(2))[0]
        if b == 252:
            return _U32.unpack(self._take(4))[0]
        if b == 253:
            return _U64.unpack(self._take(8))[0]
        raise DecodeError(f"varint marker 0x{b:02x} (u128 or invalid) where a u64 was expected", at)

    def u32(self) -> int:
        at = self.pos
        n = self.varint()
        if n > _U32_MAX:
            raise DecodeError(f"{n} does not fit a u32", at)
        return n

    def u64(self) -> int:
        return self.varint()

    def i64(self) -> int:
        z = self.varint()
        # Zigzag: 0 → 0, 1 → -1, 2 → 1, 3 → -2, ...
        return (z >> 1) ^ -(z & 1)

    def f32(self) -> float:
        return _F32.unpack(self._take(4))[0]

    def f64(self) -> float:
        return _F64.unpack(self._take(8))[0]

    def f32x3(self) -> List[float]:
        return list(_F32X3.unpack(self._take(12)))

    def f32x4(self) -> List[float]:
        return list(_F32X4.unpack(self._take(16)))

    def u8x3(self) -> List[int]:
        return list(self._take(3))

    def length(self) -> int:
        """A collection's length, checked against the bytes left (each element takes ≥ 1)."""
        at = self.pos
        n = self.varint()
        if n > len(self.buf) - self.pos:
            raise DecodeError(
                f"length {n} is more than the {len(self.buf) - self.pos} bytes left", at
            )
        return n

    def bytes(self) -> memoryview:
        return self._take(self.length())

    def string(self) -> str:
        at = self.pos
        raw = self.bytes()
        try:
            return str(raw, "utf-8")
        except UnicodeDecodeError as e:
            raise DecodeError(f"string is not UTF-8 ({e})", at) from None

    def blob(self) -> memoryview:
        """A ``Blob``: padding bytes (skipped, whatever their length), then the payload."""
        self.bytes()
        return self.bytes()

    def finish(self) -> None:
        left = len(self.buf) - self.pos
        if left:
            raise DecodeError(f"{left} bytes after the message", self.pos)


class Writer:
    """Appends bincode values to a growing buffer."""

    __slots__ = ("out",)

    def __init__(self) -> None:
        self.out = bytearray()

    def u8(self, v: int) -> None:
        if not 0 <= v <= 255:
            raise ValueError(f"{v} does not fit a u8")
        self.out.append(v)

    def bool(self, v: bool) -> None:
        self.out.append(1 if v else 0)

    def varint(self, n: int) -> None:
        if n < 0 or n > _U64_MAX:
            raise ValueError(f"{n} does not fit a u64")
        if n < 251:
            self.out.append(n)
        elif n <= 0xFFFF:
            self.out += VAR16.pack(251, n)
        elif n <= _U32_MAX:
            self.out += VAR32.pack(252, n)
        else:
            self.out += VAR64.pack(253, n)

    def u32(self, n: int) -> None:
        if n < 0 or n > _U32_MAX:
            raise ValueError(f"{n} does not fit a u32")
        self.varint(n)

    def u64(self, n: int) -> None:
        self.varint(n)

    def i64(self, n: int) -> None:
        if not -(1 << 63) <= n < (1 << 63):
            raise ValueError(f"{n} does not fit an i64")
        self.varint(((n << 1) ^ (n >> 63)) & _U64_MAX)

    def f32(self, v: float) -> None:
        self.out += _F32.pack(v)

    def f64(self, v: float) -> None:
        self.out += _F64.pack(v)

    def f32x3(self, v: Sequence[float]) -> None:
        if len(v) != 3:
            raise ValueError(f"expected 3 numbers, got {len(v)}")
        self.out += _F32X3.pack(*v)

    def f32x4(self, v: Sequence[float]) -> None:
        if len(v) != 4:
            raise ValueError(f"expected 4 numbers, got {len(v)}")
        self.out += _F32X4.pack(*v)

    def u8x3(self, v: Sequence[int]) -> None:
        if len(v) != 3:
            raise ValueError(f"expected 3 bytes, got {len(v)}")
        self.out += bytes(v)

    def bytes(self, v: Any) -> None:
        v = memoryview(v).cast("B")
        self.varint(len(v))
        self.out += v

    def string(self, v: str) -> None:
        self.bytes(v.encode("utf-8"))

    def blob(self, v: Any) -> None:
        """A ``Blob`` with an empty pad, as every request is sent."""
        self.out.append(0)
        self.bytes(v)


# ---------------------------------------------------------------------------------------------
# Type descriptions. Each has read(reader) and write(writer, value).


class _Prim:
    """A primitive type, read and written by the Reader/Writer method of the same name."""

    __slots__ = ("name", "read", "write")

    def __init__(self, name: str):
        self.name = name
        self.read: Callable[[Reader], Any] = getattr(Reader, name)
        self.write: Callable[[Writer, Any], None] = getattr(Writer, name)

    def __repr__(self) -> str:
        return self.name.upper()


U8 = _Prim("u8")
BOOL = _Prim("bool")
U32 = _Prim("u32")
U64 = _Prim("u64")
I64 = _Prim("i64")
F32 = _Prim("f32")
F64 = _Prim("f64")
F32X3 = _Prim("f32x3")
F32X4 = _Prim("f32x4")
U8X3 = _Prim("u8x3")
STR = _Prim("string")
BYTES = _Prim("bytes")
BLOB = _Prim("blob")


class Opt:
    """``Option<T>``: ``0x00`` for ``None``, else ``0x01`` then ``T``."""

    __slots__ = ("inner",)

    def __init__(self, inner: Any):
        self.inner = inner

    def read(self, r: Reader) -> Any:
        at = r.pos
        tag = r.u8()
        if tag == 0:
            return None
        if tag == 1:
            return self.inner.read(r)
        raise DecodeError(f"option tag is {tag}, not 0 or 1", at)

    def write(self, w: Writer, v: Any) -> None:
        if v is None:
            w.out.append(0)
        else:
            w.out.append(1)
            self.inner.write(w, v)


class Vec:
    """``Vec<T>``: a varint count, then the elements."""

    __slots__ = ("inner",)

    def __init__(self, inner: Any):
        self.inner = inner

    def read(self, r: Reader) -> list:
        n = r.length()
        read = self.inner.read
        return [read(r) for _ in range(n)]

    def write(self, w: Writer, v: Sequence[Any]) -> None:
        w.varint(len(v))
        write = self.inner.write
        for item in v:
            write(w, item)


class Enum:
    """A fieldless enum: its varint variant index; Python sees the lowercase variant name."""

    __slots__ = ("names",)

    def __init__(self, *names: str):
        self.names = names

    def read(self, r: Reader) -> str:
        at = r.pos
        i = r.u32()
        if i >= len(self.names):
            raise DecodeError(f"variant {i} of {'/'.join(self.names)} does not exist", at)
        return self.names[i]

    def write(self, w: Writer, v: str) -> None:
        try:
            w.varint(self.names.index(v))
        except ValueError:
            raise ValueError(f"{v!r} is not one of {', '.join(self.names)}") from None


class Tagged:
    """An enum whose variants each hold a message (``StreamMessage``): the varint variant
    index, then that variant's message. Python sees the message itself; its class says which
    variant it is."""

    __slots__ = ("classes", "msgs")

    def __init__(self, *classes: type):
        self.classes = classes
        self.msgs = [Msg(c) for c in classes]

    def read(self, r: Reader) -> Any:
        at = r.pos
        i = r.u32()
        if i >= len(self.msgs):
            names = "/".join(c.__name__ for c in self.classes)
            raise DecodeError(f"variant {i} of {names} does not exist", at)
        return self.msgs[i].read(r)

    def write(self, w: Writer, v: Any) -> None:
        for i, cls in enumerate(self.classes):
            if type(v) is cls:
                w.varint(i)
                self.msgs[i].write(w, v)
                return
        names = ", ".join(c.__name__ for c in self.classes)
        raise TypeError(f"expected one of {names}, got {type(v).__name__}")


class Msg:
    """A message: a dataclass whose ``_WIRE`` lists ``(field, type)`` in wire order."""

    __slots__ = ("cls", "fields")

    def __init__(self, cls: type):
        self.cls = cls
        self.fields = cls._WIRE

    def read(self, r: Reader) -> Any:
        return self.cls(*[t.read(r) for _, t in self.fields])

    def write(self, w: Writer, v: Any) -> None:
        if not isinstance(v, self.cls):
            raise TypeError(f"expected {self.cls.__name__}, got {type(v).__name__}")
        for name, t in self.fields:
            t.write(w, getattr(v, name))


def wire(*fields: "tuple[str, Any]") -> Callable[[type], type]:
    """Declares a dataclass's bincode layout and checks it names every field, in order."""

    def deco(cls: type) -> type:
        names = [f.name for f in dataclasses.fields(cls)]
        declared = [name for name, _ in fields]
        if names != declared:
            raise TypeError(f"{cls.__name__}: wire fields {declared} differ from {names}")
        cls._WIRE = list(fields)  # type: ignore[attr-defined]
        return cls

    return deco


def encode(value: Any) -> bytes:
    """The bincode bytes of a message (an instance of a class declared with :func:`wire`)."""
    w = Writer()
    Msg(type(value)).write(w, value)
    return bytes(w.out)


def decode(cls: type, data: Any) -> Any:
    """Decodes one whole message of class ``cls``; trailing bytes are an error."""
    return decode_as(Msg(cls), data)


def encode_as(typ: Any, value: Any) -> bytes:
    """The bincode bytes of ``value`` as the type description ``typ`` (``Tagged(...)``...)."""
    w = Writer()
    typ.write(w, value)
    return bytes(w.out)


def decode_as(typ: Any, data: Any) -> Any:
    """Decodes one whole value of the type description ``typ``; trailing bytes are an error."""
    r = Reader(data)
    value = typ.read(r)
    r.finish()
    return value

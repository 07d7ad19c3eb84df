"""msgpack on the wire without copying arrays: a chunked writer and a zero-copy reader.

`msgpack.packb` copies every array into its growing buffer (several times, as it
grows) and `msgpack.unpackb` copies every `bin` value into a new `bytes`: for a
1.28 MB map message that was 0.4 ms of the bus's 1 ms (docs/bus.md). Here a
message is written as a list of chunks, array buffers among them, joined once
(`bin_header` and `map_header` write what msgpack would, so the bytes are
`msgpack.packb`'s), and `read` parses the payload itself, returning each `bin`
value as a `memoryview` into it: an array decoded from it is a view of the
payload, not a copy. `read` takes every msgpack type but `ext` (no message uses
one) and raises `WireError` on anything else, truncated or left over.
"""

from __future__ import annotations

import struct
from typing import Any

_U8 = struct.Struct(">B").unpack_from
_U16 = struct.Struct(">H").unpack_from
_U32 = struct.Struct(">I").unpack_from
_U64 = struct.Struct(">Q").unpack_from
_I8 = struct.Struct(">b").unpack_from
_I16 = struct.Struct(">h").unpack_from
_I32 = struct.Struct(">i").unpack_from
_I64 = struct.Struct(">q").unpack_from
_F32 = struct.Struct(">f").unpack_from
_F64 = struct.Struct(">d").unpack_from

MAX_DEPTH = 32          # nesting of arrays and maps (messages use 4)


class WireError(ValueError):
    """Not one well-formed msgpack value."""


# ----------------------------------------------------------------------------- writing
def bin_header(n: int) -> bytes:
    """The msgpack `bin` header for n bytes (bin 8 / 16 / 32, as msgpack writes it)."""
    if n < 1 << 8:
        return b"\xc4" + n.to_bytes(1, "big")
    if n < 1 << 16:
        return b"\xc5" + n.to_bytes(2, "big")
    if n < 1 << 32:
        return b"\xc6" + n.to_bytes(4, "big")
    raise WireError(f"a bin of {n} bytes does not fit msgpack")


def map_header(n: int) -> bytes:
    """The msgpack map header for n entries (fixmap / map 16 / map 32)."""
    if n < 16:
        return bytes((0x80 | n,))
    if n < 1 << 16:
        return b"\xde" + n.to_bytes(2, "big")
    return b"\xdf" + n.to_bytes(4, "big")


# ----------------------------------------------------------------------------- reading
def read(payload: bytes) -> Any:
    """The one msgpack value `payload` holds; `bin` values are memoryviews into it."""
    buf = memoryview(payload)
    if buf.ndim != 1 or buf.itemsize != 1:
        buf = buf.cast("B")
    try:
        value, end = _value(buf, 0, 0)
    except (IndexError, struct.error):
        raise WireError(f"truncated: {len(buf)} bytes end inside a value") from None
    except UnicodeDecodeError as exc:
        raise WireError(f"a string is not UTF-8: {exc.reason}") from None
    if end != len(buf):
        raise WireError(f"{len(buf) - end} bytes left over after the value")
    return value


def _take(buf: memoryview, pos: int, n: int) -> tuple[memoryview, int]:
    end = pos + n
    if end > len(buf):
        raise IndexError
    return buf[pos:end], end


def _value(buf: memoryview, pos: int, depth: int) -> tuple[Any, int]:
    b = buf[pos]
    pos += 1
    if b < 0x80:                                   # positive fixint
        return b, pos
    if b >= 0xe0:                                  # negative fixint
        return b - 0x100, pos
    if b >= 0xa0 and b < 0xc0:                     # fixstr
        s, pos = _take(buf, pos, b & 0x1f)
        return str(s, "utf-8"), pos
    if b < 0x90:                                   # fixmap
        return _map(buf, pos, b & 0x0f, depth)
    if b < 0xa0:                                   # fixarray
        return _array(buf, pos, b & 0x0f, depth)
    if b == 0xc0:
        return None, pos
    if b == 0xc2:
        return False, pos
    if b == 0xc3:
        return True, pos
    if b == 0xc4 or b == 0xc5 or b == 0xc6:       # bin 8 / 16 / 32: no copy
        n, pos = _length(buf, pos, b - 0xc4)
        return _take(buf, pos, n)
    if b == 0xca:
        return _F32(buf, pos)[0], pos + 4
    if b == 0xcb:
        return _F64(buf, pos)[0], pos + 8
    if 0xcc <= b <= 0xd3:                          # uint 8..64, int 8..64
        unpack, size = _INTS[b - 0xcc]
        return unpack(buf, pos)[0], pos + size
    if b == 0xd9 or b == 0xda or b == 0xdb:       # str 8 / 16 / 32
        n, pos = _length(buf, pos, b - 0xd9)
        s, pos = _take(buf, pos, n)
        return str(s, "utf-8"), pos
    if b == 0xdc or b == 0xdd:                     # array 16 / 32
        n, pos = _length(buf, pos, b - 0xdb)
        return _array(buf, pos, n, depth)
    if b == 0xde or b == 0xdf:                     # map 16 / 32
        n, pos = _length(buf, pos, b - 0xdd)
        return _map(buf, pos, n, depth)
    if b == 0xc1:
        raise WireError("byte 0xc1 is never used by msgpack")
    raise WireError(f"ext type 0x{b:02x} at byte {pos - 1}: no message uses one")


_INTS = ((_U8, 1), (_U16, 2), (_U32, 4), (_U64, 8), (_I8, 1), (_I16, 2), (_I32, 4), (_I64, 8))
_LENGTHS = ((_U8, 1), (_U16, 2), (_U32, 4))


def _length(buf: memoryview, pos: int, width: int) -> tuple[int, int]:
    unpack, size = _LENGTHS[width]
    return unpack(buf, pos)[0], pos + size


def _array(buf: memoryview, pos: int, n: int, depth: int) -> tuple[list, int]:
    if depth >= MAX_DEPTH:
        raise WireError(f"nested deeper than {MAX_DEPTH}")
    if n > len(buf) - pos:                         # every element takes a byte at least
        raise IndexError
    out = []
    for _ in range(n):
        v, pos = _value(buf, pos, depth + 1)
        out.append(v)
    return out, pos


def _map(buf: memoryview, pos: int, n: int, depth: int) -> tuple[dict, int]:
    if depth >= MAX_DEPTH:
        raise WireError(f"nested deeper than {MAX_DEPTH}")
    if 2 * n > len(buf) - pos:
        raise IndexError
    out = {}
    for _ in range(n):
        k, pos = _value(buf, pos, depth + 1)
        if not isinstance(k, str):
            raise WireError(f"a map key is a {type(k).__name__}, not a string")
        out[k], pos = _value(buf, pos, depth + 1)
    return out, pos

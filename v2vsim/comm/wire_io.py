"""The primitives of the V2V wire layout (v2vsim.comm.codec) that encoding, decoding and signing share:
the little-endian integer structs, length-bounded utf-8, the finiteness check on arrays, and `Reader`,
the bounds-checked cursor a receiver parses with (running off the end is RejectedMessage('truncated'))."""

from __future__ import annotations

import struct

import numpy as np

from v2vsim.comm.message import RejectedMessage

__all__ = ["U8", "U16", "U32", "Reader", "all_finite", "utf8"]

U8 = struct.Struct("<B")
U16 = struct.Struct("<H")
U32 = struct.Struct("<I")


def all_finite(a: np.ndarray) -> bool:
    """np.isfinite(a).all(), but on float16 via the exponent bits (numpy's float16 ufuncs are slow).

    Integer arrays are finite by construction."""
    if a.size == 0 or a.dtype.kind != "f":
        return True
    if a.dtype == np.float16:
        return int((a.view(np.uint16) & 0x7FFF).max()) < 0x7C00
    return bool(np.isfinite(a).all())


def utf8(s: str, what: str, limit: int) -> bytes:
    """`s` as utf-8, at most `limit` bytes long; ValueError (a sender's mistake) otherwise."""
    b = s.encode("utf-8")
    if len(b) > limit:
        raise ValueError(f"{what} longer than {limit} bytes: {s[:40]!r}...")
    return b


class Reader:
    """Bounds-checked cursor: running off the end is 'truncated', never an IndexError."""

    def __init__(self, data: bytes | memoryview, end: int) -> None:
        self.data = data
        self.pos = 0
        self.end = end

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > self.end:
            raise RejectedMessage("truncated", f"need {n} bytes at offset {self.pos}, have {self.end - self.pos}")
        out = memoryview(self.data)[self.pos:self.pos + n]
        self.pos += n
        return out

    def unpack(self, st: struct.Struct) -> tuple:
        return st.unpack(self.take(st.size))

    def text(self, what: str) -> str:
        (n,) = self.unpack(U16)
        try:
            return bytes(self.take(n)).decode("utf-8")
        except UnicodeDecodeError:
            raise RejectedMessage("bad_header", f"{what} is not utf-8") from None

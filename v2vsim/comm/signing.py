"""Signing and verifying V2V messages under comm.auth (the wire layout is v2vsim.comm.codec's).

A `Signer` is the run's shared key (hmac-sha256, a 32-byte tag: FLAG_SIGNED, membership) or a process's
`Identity` (Ed25519, a 64-byte signature: FLAG_IDENTITY, who; v2vsim.comm.identity). Either covers every
byte before it and is appended last. The sending side: `signature_flag` (the header's flag bit),
`check_signer` (an Identity signs only as the CAV agent of the sender id) and `signature` (the tag).
The receiving side: `authenticated_header`, the checks every receiver runs first (magic, version, fixed
header, flags, then the signature), so unauthenticated bytes never reach zlib or numpy.
"""

from __future__ import annotations

import hashlib
import hmac

from v2vsim.comm.identity import Identity, data_signer
from v2vsim.comm.message import (
    _FIXED,
    _KNOWN_FLAGS,
    FLAG_IDENTITY,
    FLAG_SIGNED,
    MAGIC,
    SIG_LEN,
    TAG_LEN,
    VERSION,
    RejectedMessage,
)
from v2vsim.comm.wire_io import U32, Reader

__all__ = ["Signer", "authenticated_header", "check_signer", "signature", "signature_flag"]

Signer = bytes | Identity
"""What signs and checks messages under comm.auth: the run's shared key (hmac-sha256: membership), or a
process's Identity (Ed25519: who; v2vsim.comm.identity)."""


def signature_flag(key: Signer | None) -> int:
    """The header flag that says which tag `key` appends: none, FLAG_IDENTITY or FLAG_SIGNED."""
    return 0 if key is None else FLAG_IDENTITY if isinstance(key, Identity) else FLAG_SIGNED


def check_signer(key: Signer | None, sender_id: str) -> None:
    """ValueError unless `key` may sign a message of `sender_id`: an Identity signs only as its own
    process, which must be the CAV agent the sender id names (a shared key signs any)."""
    if isinstance(key, Identity) and key.name != data_signer(sender_id):
        raise ValueError(f"{key.name} cannot sign a message of sender {sender_id!r}")


def signature(data: bytes, key: Signer | None) -> bytes:
    """The tag that follows `data` on the wire: the Ed25519 signature of an Identity, the hmac-sha256 of
    a shared key, or nothing without a key."""
    if isinstance(key, Identity):
        return key.sign(data)
    if key is not None:
        return hmac.new(key, data, hashlib.sha256).digest()
    return b""


def authenticated_header(data: bytes, key: Signer | None) -> tuple[int, int, int, int, Reader]:
    """(frame, kind code, flags, end of the signed bytes, a reader after the fixed header): the checks
    every receiver runs first, the signature included, so unauthenticated bytes go no further."""
    if len(data) < 5:
        raise RejectedMessage("truncated", f"{len(data)} bytes")
    if data[:4] != MAGIC:
        raise RejectedMessage("bad_magic", repr(data[:4]))
    if data[4] != VERSION:
        raise RejectedMessage("bad_version", f"version {data[4]}, this build reads {VERSION}")
    if len(data) < _FIXED.size:
        raise RejectedMessage("truncated", f"{len(data)} bytes, the fixed header alone is {_FIXED.size}")
    flags, frame = data[6], U32.unpack_from(data, 12)[0]
    if flags & ~_KNOWN_FLAGS:
        raise RejectedMessage("bad_header", f"unknown flags 0x{flags:02x}")
    if flags & FLAG_SIGNED and flags & FLAG_IDENTITY:
        raise RejectedMessage("bad_header", "two signatures")
    tag_len = TAG_LEN if flags & FLAG_SIGNED else SIG_LEN if flags & FLAG_IDENTITY else 0
    end = len(data) - tag_len
    if end < _FIXED.size:
        raise RejectedMessage("truncated", "no room for the signature")
    if isinstance(key, Identity):
        if not flags & FLAG_IDENTITY:
            raise RejectedMessage("unsigned", "comm.auth.identity is per_process and the message carries no "
                                              "process signature")
        r = Reader(data, end)
        r.pos = _FIXED.size
        r.text("run id")
        signer = data_signer(r.text("sender id"))
        if not key.verify(signer, memoryview(data)[:end], memoryview(data)[end:]):
            raise RejectedMessage("bad_signature", f"not signed by {signer}")
    elif key is not None:
        if not flags & FLAG_SIGNED:
            raise RejectedMessage("unsigned", "comm.auth is on and the message carries no signature")
        tag = hmac.new(key, memoryview(data)[:end], hashlib.sha256).digest()
        if not hmac.compare_digest(tag, data[end:]):
            raise RejectedMessage("bad_signature")
    r = Reader(data, end)
    r.pos = _FIXED.size
    return frame, data[5], flags, end, r

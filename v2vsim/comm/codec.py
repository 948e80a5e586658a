"""The V2V wire format (DESIGN.md "V2V message"): a versioned binary header and array payload.

Layout (little endian), version 1::

    fixed   "<4sBBBBHHIddddd" : magic b"V2VS", version, kind, flags, compression,
                               channel_compression, n_arrays, frame, capture_time, x, y, z, yaw
    run id  "<H" length + utf-8 bytes
    sender  "<H" length + utf-8 bytes
    space   "<H" length + utf-8 bytes, only when flags & FLAG_SPACE: "<encoder>@<feature space>" (Message.space)
    arrays  n_arrays x ("<B" name length + utf-8 name, "<BB" dtype, ndim, "<ndim I" shape)
    payload "<I" length + the arrays' bytes back to back (zlib-compressed as one block if compressed)
    tag     32 bytes hmac-sha256 under the run key over everything before it (only when flags & FLAG_SIGNED),
            or 64 bytes, the sending process's Ed25519 signature over everything before it (only when
            flags & FLAG_IDENTITY; comm.auth.identity per_process, v2vsim.comm.identity): the signer is
            the CAV agent the sender id names, checked against the run's trust list

Array 0 is the message's `payload`; the others are `extras` (late-fusion boxes, say).
Dtype codes: 1 float16, 2 float32, 3 uint16, 4 uint32, 5 uint8. The payload always has its kind's
dtype; an extra may have any of them: uint16/32 only as the cell indices ("cells"), uint8 only as the
sender's packed free-space evidence ("evidence", v2vsim.perception.evidence).

Kinds and their primary payload:
  * "features": BEV feature map (C, H, W), float16 on the wire.
  * "points":   raw points for early fusion (P, 4) x, y, z, intensity, float32.
  * "outputs":  per-CAV outputs for late fusion: segmentation probabilities (K, H, W) float16,
                plus extras such as "boxes" (N, 8) float32 (x, y, z, l, w, h, yaw, score).
  * "sparse":   some cells of a BEV feature map (Where2comm): values (N, C) float16, plus the
                required extra "cells" (N,) uint16/uint32, the cells' row-major indices into
                the F x F grid, strictly increasing (v2vsim.comm.sparse builds and expands it).

`channel_compression` is the learned channel-reduction ratio of CoBEVT Table 4 (8x-64x):
the 1x1-conv encoder/decoder pair lives in models/, so a "features" or "sparse" payload with
ratio r already carries C/r channels; the header only records r so the receiver picks the matching
decoder. 1 means off. Lossless `compression` ("zlib") is separate and applies to the payload.

A message that fails any check raises `RejectedMessage(reason)` and nothing else, so a
receiving process can count it and carry on.

What a receiver accepts is a `KindSpec` per kind (`decode(..., spec=...)`): the payload's shape
(exact sizes or `AtMost(n)` bounds) and exactly which extras it must carry. Every check that
bounds memory (kind, names, shapes, the total declared size, the message length) runs before
the payload is inflated or copied, so a 1 MB zlib bomb declaring 67 M points costs nothing.
Under a spec an integer extra is accepted only as the index extra "cells" of a kind whose
KindSpec sets `cells` (the grid size); its values are checked after decoding ('bad_indices'),
since a receiver scatters the payload with them.

This module holds the encoder and the decoder (`encode`, `check_arrival`, `decode`) and re-exports the
message model they speak (v2vsim.comm.message). The tag's signing and the checks every receiver runs before
parsing (magic, version, flags, signature) are v2vsim.comm.signing; the shared parsing primitives are
v2vsim.comm.wire_io.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Collection, Mapping

import numpy as np

from v2vsim.comm.message import (
    _COMPRESSION_NAMES,
    _DTYPE_NAMES,
    _FIXED,
    _INDEX_DTYPES,
    _KIND_NAMES,
    CELLS,
    COMPRESSION_CODES,
    DTYPE_CODES,
    EVIDENCE,
    FLAG_IDENTITY,
    FLAG_SIGNED,
    FLAG_SPACE,
    KIND_CODES,
    KIND_DTYPES,
    MAGIC,
    MAX_NDIM,
    MAX_PAYLOAD_BYTES,
    REASONS,
    SIG_LEN,
    TAG_LEN,
    VERSION,
    AtMost,
    Compression,
    Dim,
    Kind,
    KindSpec,
    Message,
    RejectedMessage,
    ShapeSpec,
    encoded_size_hint,
)
from v2vsim.comm.signing import Signer, authenticated_header, check_signer, signature, signature_flag
from v2vsim.comm.wire_io import U8, U16, U32, all_finite, utf8

__all__ = [
    "CELLS", "COMPRESSION_CODES", "DTYPE_CODES", "EVIDENCE", "FLAG_IDENTITY", "FLAG_SIGNED", "FLAG_SPACE", "KIND_CODES",
    "KIND_DTYPES",
    "MAGIC", "MAX_NDIM", "MAX_PAYLOAD_BYTES", "REASONS", "SIG_LEN", "TAG_LEN", "VERSION", "AtMost", "Compression",
    "Dim", "Kind", "KindSpec", "Message", "RejectedMessage", "ShapeSpec", "Signer", "check_arrival", "decode",
    "encode", "encoded_size_hint",
]

def encode(msg: Message, key: Signer | None = None, *, check_finite: bool = True) -> bytes:
    """Serialise `msg` (casting the payload to its kind's wire dtype); sign it when `key` is given (an
    Identity signs as its own process, which must be the CAV agent of msg.sender_id).

    Extras keep a wire dtype (float16/32, uint16/32; uint8 only as "evidence"); any other dtype is cast to
    float32, so indices must already be uint16/uint32 (v2vsim.comm.sparse.index_dtype) to stay integers.

    Raises ValueError for a message that the receiver would reject anyway (non-finite values
    after the cast, an unknown kind); `check_finite=False` is for tests that need such bytes.
    """
    if msg.kind not in KIND_CODES:
        raise ValueError(f"unknown kind {msg.kind!r}; allowed: {', '.join(KIND_CODES)}")
    if msg.compression not in COMPRESSION_CODES:
        raise ValueError(f"unknown compression {msg.compression!r}; allowed: {', '.join(COMPRESSION_CODES)}")
    if not 1 <= int(msg.channel_compression) <= 0xFFFF:
        raise ValueError(f"channel_compression must be 1..65535, got {msg.channel_compression}")
    if not 0 <= int(msg.frame) <= 0xFFFFFFFF:
        raise ValueError(f"frame must fit in uint32, got {msg.frame}")
    with np.errstate(over="ignore"):  # an overflow to inf is caught by the finiteness check below
        primary = np.asarray(msg.payload, dtype=KIND_DTYPES[msg.kind])
    arrays: list[tuple[str, np.ndarray]] = [("", primary)]
    for name, arr in msg.extras.items():
        if not name:
            raise ValueError("extra arrays need a non-empty name")
        a = np.asarray(arr)
        if a.dtype.name not in DTYPE_CODES or (a.dtype.name == "uint8") != (name == EVIDENCE):
            with np.errstate(over="ignore"):
                a = a.astype(np.float32)
        arrays.append((name, a))
    if len(arrays) > 0xFFFF:
        raise ValueError("too many extra arrays")

    parts: list[bytes | memoryview] = []
    x, y, z, yaw = (float(v) for v in msg.sender_pose)
    flags = signature_flag(key)
    if msg.space:
        flags |= FLAG_SPACE
    check_signer(key, msg.sender_id)
    parts.append(_FIXED.pack(MAGIC, VERSION, KIND_CODES[msg.kind], flags, COMPRESSION_CODES[msg.compression],
                             int(msg.channel_compression), len(arrays), int(msg.frame),
                             float(msg.capture_time), x, y, z, yaw))
    texts = [(msg.run_id, "run id"), (msg.sender_id, "sender id")] + ([(msg.space, "space")] if msg.space else [])
    for text, what in texts:
        b = utf8(text, what, 0xFFFF)
        parts += [U16.pack(len(b)), b]
    blobs: list[memoryview] = []
    for name, a in arrays:
        if a.ndim > MAX_NDIM or any(d > 0xFFFFFFFF for d in a.shape):
            raise ValueError(f"array {name or 'payload'} shape {a.shape} not representable")
        if check_finite and not all_finite(a):
            raise ValueError(f"array {name or 'payload'} has NaN/Inf values (after the cast to {a.dtype})")
        nb = utf8(name, "extra name", 0xFF)
        parts += [U8.pack(len(nb)), nb, struct.pack(f"<BB{a.ndim}I", DTYPE_CODES[a.dtype.name], a.ndim, *a.shape)]
        le = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))  # no copy on x86/arm
        blobs.append(memoryview(le.reshape(-1).view(np.uint8)))
    body: bytes | memoryview = blobs[0] if len(blobs) == 1 else b"".join(blobs)
    if msg.compression == "zlib":
        body = zlib.compress(body, 1)  # level 1: float payloads gain little from harder work
    parts += [U32.pack(len(body)), body]
    data = b"".join(parts)
    return data if key is None else data + signature(data, key)


def _shape_ok(shape: tuple[int, ...], spec: ShapeSpec) -> bool:
    return len(shape) == len(spec) and all(
        s is None or (d <= s.n if isinstance(s, AtMost) else s == d) for d, s in zip(shape, spec, strict=True))


def check_arrival(data: bytes, *, key: Signer | None = None, run_id: str | None = None,
                  known_senders: Collection[str] | None = None) -> tuple[int, str]:
    """(frame, sender id) of a message as it comes off the transport, after the checks that cost
    next to nothing or must come first: magic, version, the fixed header, the signature when `key`
    is given (so a forged message never takes a receiver's buffer), the run and the sender. The
    payload is not looked at: `decode` does the rest when the message is fused."""
    try:
        frame, _kind, _flags, _end, r = authenticated_header(data, key)
        msg_run, sender = r.text("run id"), r.text("sender id")
    except RejectedMessage:
        raise
    except Exception as e:
        raise RejectedMessage("bad_header", f"internal: {type(e).__name__}: {e}") from None
    if run_id is not None and msg_run != run_id:
        raise RejectedMessage("wrong_run", f"{msg_run!r} != {run_id!r}")
    if known_senders is not None and sender not in known_senders:
        raise RejectedMessage("unknown_sender", repr(sender))
    return frame, sender


def decode(data: bytes | bytearray | memoryview, *, key: Signer | None = None,
           known_senders: Collection[str] | None = None,
           expected: Mapping[str, ShapeSpec] | None = None,
           run_id: str | None = None,
           spec: Mapping[str, KindSpec] | None = None) -> Message:
    """Parse and validate one message; raise RejectedMessage(reason) on any problem.

    key: when set, the message must carry a valid hmac-sha256 tag under this run key, or, for an
         Identity, its sender's process signature ('unsigned' / 'bad_signature'); when None, a tag,
         if present, is stripped without being checked.
    known_senders: when set, other sender ids are 'unknown_sender'.
    spec: kind -> KindSpec, the strict form a receiver should use: payload shape, required and
         allowed extras, and a bound on every size. Kinds missing from it are 'unexpected_kind'.
    expected: the older, lax form (no `spec`): kind -> shape spec; extras are checked under
         "kind.name" keys when present, others pass. Kinds missing from it are 'unexpected_kind'.
    run_id: when set, messages of another run are 'wrong_run'.
    """
    if spec is not None and expected is not None:
        raise TypeError("decode: give `spec` or `expected`, not both")
    try:
        return _decode(data, key, known_senders, expected, run_id, spec)
    except RejectedMessage:
        raise
    except Exception as e:  # a bug or an input no check foresaw: still a rejection, never a crash
        raise RejectedMessage("bad_header", f"internal: {type(e).__name__}: {e}") from None


def _decode(data: bytes | bytearray | memoryview, key: Signer | None, known_senders: Collection[str] | None,
            expected: Mapping[str, ShapeSpec] | None, run_id: str | None,
            spec: Mapping[str, KindSpec] | None) -> Message:
    if spec is not None and len(data) >= 6 and data[5] in _KIND_NAMES and _KIND_NAMES[data[5]] in spec:
        # Refuse what no accepted message can be as long as, before hashing or copying it.
        limit = spec[_KIND_NAMES[data[5]]].max_message_bytes(_KIND_NAMES[data[5]])
        if limit is not None and len(data) > limit:
            raise RejectedMessage("size_mismatch", f"{len(data)} bytes, the longest acceptable is {limit}")
    data = bytes(data) if not isinstance(data, bytes) else data
    # Authenticate before parsing further, so unauthenticated bytes never reach zlib or numpy.
    _, _, _, end, r = authenticated_header(data, key)
    (_, _, kind_code, flags, comp_code, ch_comp, n_arrays, frame, capture_time,
     x, y, z, yaw) = _FIXED.unpack_from(data)
    if kind_code not in _KIND_NAMES:
        raise RejectedMessage("unknown_kind", f"code {kind_code}")
    kind = _KIND_NAMES[kind_code]
    if comp_code not in _COMPRESSION_NAMES:
        raise RejectedMessage("bad_header", f"unknown compression code {comp_code}")
    if ch_comp < 1:
        raise RejectedMessage("bad_header", "channel_compression 0")
    if n_arrays < 1:
        raise RejectedMessage("bad_header", "no payload array")
    if not all(math.isfinite(v) for v in (capture_time, x, y, z, yaw)):
        raise RejectedMessage("non_finite", "capture time or pose")

    msg_run = r.text("run id")
    sender = r.text("sender id")
    space = r.text("space") if flags & FLAG_SPACE else ""
    if run_id is not None and msg_run != run_id:
        raise RejectedMessage("wrong_run", f"{msg_run!r} != {run_id!r}")
    if known_senders is not None and sender not in known_senders:
        raise RejectedMessage("unknown_sender", repr(sender))
    if expected is not None and kind not in expected:
        raise RejectedMessage("unexpected_kind", kind)
    kspec = None
    limit = MAX_PAYLOAD_BYTES
    if spec is not None:
        if kind not in spec:
            raise RejectedMessage("unexpected_kind", kind)
        kspec = spec[kind]
        if kspec.spaces is not None and space.partition("@")[2] not in kspec.spaces:
            raise RejectedMessage("foreign_space", f"{sender!r} sent {kind} of {space or 'an unnamed space'!r}; "
                                                   f"this receiver fuses {', '.join(sorted(kspec.spaces))}")
        if kspec.channel_compression is not None and ch_comp != kspec.channel_compression:
            raise RejectedMessage("bad_header", f"channel_compression {ch_comp}, this receiver decodes "
                                                f"{kspec.channel_compression}")
        if n_arrays > 1 + len(kspec.extras):
            raise RejectedMessage("unexpected_extra", f"{n_arrays - 1} extras, {kind} carries at most "
                                                      f"{len(kspec.extras)}")
        bound = kspec.max_payload_bytes(kind)
        limit = limit if bound is None else min(limit, bound)

    specs: list[tuple[str, np.dtype, tuple[int, ...]]] = []
    total = 0
    for i in range(n_arrays):
        (nlen,) = r.unpack(U8)
        try:
            name = bytes(r.take(nlen)).decode("utf-8")
        except UnicodeDecodeError:
            raise RejectedMessage("bad_header", "array name is not utf-8") from None
        if kspec is not None:
            if i == 0 and name:
                raise RejectedMessage("bad_header", f"the payload array is named {name!r}")
            if i > 0 and name not in kspec.extras:
                raise RejectedMessage("unexpected_extra", f"{kind} extra {name!r}")
            if any(name == seen for seen, _, _ in specs):
                raise RejectedMessage("bad_header", f"duplicate array {name!r}")
        dtype_code, ndim = r.unpack(struct.Struct("<BB"))
        if dtype_code not in _DTYPE_NAMES:
            raise RejectedMessage("unknown_dtype", f"code {dtype_code}")
        dtype = np.dtype(_DTYPE_NAMES[dtype_code]).newbyteorder("<")
        if i == 0 and dtype.name != KIND_DTYPES[kind]:
            raise RejectedMessage("unknown_dtype", f"{kind} must be {KIND_DTYPES[kind]}, got {dtype.name}")
        if (kspec is not None and i > 0 and dtype.name in _INDEX_DTYPES
                and not (kspec.cells is not None and name == CELLS)):
            raise RejectedMessage("unknown_dtype", f"{kind} extra {name!r} must be float, got {dtype.name}")
        if i > 0 and (dtype.name == "uint8") != (name == EVIDENCE):
            raise RejectedMessage("unknown_dtype", f"{kind} extra {name!r} of dtype {dtype.name}: only "
                                                   f"{EVIDENCE!r} is uint8, and it is nothing else")
        if ndim > MAX_NDIM:
            raise RejectedMessage("shape_mismatch", f"ndim {ndim}")
        shape = tuple(r.unpack(struct.Struct(f"<{ndim}I")))
        spec_key = kind if i == 0 else f"{kind}.{name}"
        want = None
        if kspec is not None:
            want = kspec.payload if i == 0 else kspec.extras[name]
        elif expected is not None:
            want = expected.get(spec_key)
        if want is not None and not _shape_ok(shape, want):
            raise RejectedMessage("shape_mismatch", f"{spec_key} shape {shape}, expected {want}")
        nbytes = math.prod(shape) * dtype.itemsize
        total += nbytes
        if total > limit:
            raise RejectedMessage("size_mismatch", f"declared payload of {total} bytes, at most {limit}")
        specs.append((name, dtype, shape))
    if len({name for name, _, _ in specs}) != len(specs):
        raise RejectedMessage("bad_header", "duplicate array names")
    if kspec is not None:
        missing = set(kspec.extras) - kspec.optional - {name for name, _, _ in specs}
        if missing:
            raise RejectedMessage("missing_extra", f"{kind} without {', '.join(sorted(missing))}")

    (body_len,) = r.unpack(U32)
    body = r.take(body_len)
    if r.pos != end:
        raise RejectedMessage("size_mismatch", f"{end - r.pos} trailing bytes")
    if comp_code == COMPRESSION_CODES["zlib"]:
        d = zlib.decompressobj()
        try:
            raw = d.decompress(body, total + 1)  # bounded: a zlib bomb cannot inflate past the declared size
        except zlib.error as e:
            raise RejectedMessage("decompress_error", str(e)) from None
        if len(raw) != total or not d.eof or d.unconsumed_tail or d.unused_data:
            raise RejectedMessage("size_mismatch", f"inflated to {len(raw)}+ bytes, header says {total}")
    else:
        raw = body
        if len(raw) != total:
            raise RejectedMessage("size_mismatch", f"payload {len(raw)} bytes, header says {total}")

    arrays: list[tuple[str, np.ndarray]] = []
    off = 0
    for name, dtype, shape in specs:
        n = math.prod(shape) * dtype.itemsize
        a = np.frombuffer(raw, dtype=dtype, count=math.prod(shape), offset=off).reshape(shape)
        a = a.astype(dtype.newbyteorder("="), copy=True)  # own, writable, native-order memory
        off += n
        if not all_finite(a):
            raise RejectedMessage("non_finite", f"array {name or 'payload'}")
        arrays.append((name, a))
    if kspec is not None and kspec.cells is not None:
        _check_cells(dict(arrays[1:])[CELLS], arrays[0][1], kspec.cells)
    return Message(kind=kind, run_id=msg_run, sender_id=sender, frame=frame, capture_time=capture_time,
                   sender_pose=(x, y, z, yaw), payload=arrays[0][1],
                   compression=_COMPRESSION_NAMES[comp_code],  # type: ignore[arg-type]
                   channel_compression=ch_comp, extras=dict(arrays[1:]), space=space)


def _check_cells(cells: np.ndarray, payload: np.ndarray, n_cells: int) -> None:
    """Indices a receiver can scatter `payload` rows with: one integer per row, < n_cells, strictly
    increasing (so unique); else RejectedMessage('bad_indices')."""
    if cells.dtype.name not in _INDEX_DTYPES:
        raise RejectedMessage("bad_indices", f"{CELLS} of dtype {cells.dtype.name}, not uint16/uint32")
    rows = payload.shape[0] if payload.ndim else None
    if cells.shape != (rows,):
        raise RejectedMessage("bad_indices", f"{CELLS} shape {cells.shape} for payload rows {rows}")
    if cells.size == 0:
        return
    if int(cells.max()) >= n_cells:
        raise RejectedMessage("bad_indices", f"cell {int(cells.max())} outside a grid of {n_cells}")
    if not bool((cells[1:] > cells[:-1]).all()):
        raise RejectedMessage("bad_indices", f"{CELLS} not strictly increasing")

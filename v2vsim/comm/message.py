"""The V2V message model and its limits (the wire format itself is v2vsim.comm.codec): the kinds,
dtype and compression codes, header constants and size bounds, what a receiver accepts (`KindSpec`,
`AtMost`), the stable rejection reasons (`RejectedMessage`) and the `Message` itself."""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal, TypeAlias

import numpy as np

MAGIC = b"V2VS"
VERSION = 1
FLAG_SIGNED = 0x01  # tag: hmac-sha256 under the run's shared key (comm.auth.key_file)
FLAG_IDENTITY = 0x02  # tag: the sending process's Ed25519 signature (comm.auth.identity per_process)
FLAG_SPACE = 0x04  # the header names the encoder and feature space that made the payload (a mixed fleet)
_KNOWN_FLAGS = FLAG_SIGNED | FLAG_IDENTITY | FLAG_SPACE
TAG_LEN = 32  # hmac-sha256
SIG_LEN = 64  # Ed25519
MAX_PAYLOAD_BYTES = 256 << 20  # declared sizes above this are refused before any allocation (no spec given)
MAX_NDIM = 8

Kind = Literal["features", "points", "outputs", "sparse"]
Compression = Literal["none", "zlib"]

KIND_CODES: dict[str, int] = {"features": 1, "points": 2, "outputs": 3, "sparse": 4}
_KIND_NAMES = {v: k for k, v in KIND_CODES.items()}
COMPRESSION_CODES: dict[str, int] = {"none": 0, "zlib": 1}
_COMPRESSION_NAMES = {v: k for k, v in COMPRESSION_CODES.items()}
DTYPE_CODES: dict[str, int] = {"float16": 1, "float32": 2, "uint16": 3, "uint32": 4, "uint8": 5}
_DTYPE_NAMES = {v: k for k, v in DTYPE_CODES.items()}
_INDEX_DTYPES = frozenset({"uint16", "uint32"})
# The wire dtype of each kind's primary payload; extras may have any dtype of DTYPE_CODES.
KIND_DTYPES: dict[str, str] = {"features": "float16", "points": "float32", "outputs": "float16",
                               "sparse": "float16"}
CELLS = "cells"
"""The name of the index extra checked against KindSpec.cells (the "sparse" kind's cell indices)."""
EVIDENCE = "evidence"
"""The one extra that is raw bytes (uint8): a sender's packed free-space evidence (v2vsim.perception.evidence)."""

# The fixed header of v2vsim.comm.codec's layout; its size bounds KindSpec.max_message_bytes.
_FIXED = struct.Struct("<4sBBBBHHIddddd")


@dataclass(frozen=True)
class AtMost:
    """A dimension of any size from 0 to `n` (a point count, a box count): bounded, unlike None."""

    n: int


Dim: TypeAlias = int | AtMost | None
ShapeSpec: TypeAlias = tuple[Dim, ...]
"""An expected shape: a fixed length, each entry an exact size, an AtMost bound, or None for 'any'."""


@dataclass(frozen=True)
class KindSpec:
    """What a receiver accepts for one kind: the payload's shape and the extras it carries.

    extras: name -> shape of every extra allowed; each one is required unless named in
    `optional`. Any other extra is 'unexpected_extra', a missing one 'missing_extra'.
    channel_compression: the ratio the header must name (the receiver's decoder is built for
    one), None for any.
    cells: the number of cells of the dense grid that the required extra "cells" indexes, None
    when the kind carries no indices. The receiver scatters payload rows into those cells, so
    they must be integers, one per row, in range and strictly increasing ('bad_indices').
    spaces: the feature spaces the receiver can fuse (Message.space after its "@"); a message naming
    another, or none, is 'foreign_space'; None accepts any.
    """

    payload: ShapeSpec
    extras: Mapping[str, ShapeSpec] = field(default_factory=dict)
    optional: frozenset[str] = frozenset()
    channel_compression: int | None = 1
    cells: int | None = None
    # the feature spaces accepted (the part of Message.space after "@"); None: any, a space named or not
    spaces: frozenset[str] | None = None

    def __post_init__(self) -> None:
        if self.cells is not None and (self.cells < 1 or CELLS not in self.extras or CELLS in self.optional):
            raise ValueError(f"KindSpec(cells={self.cells}) needs cells >= 1 and a required {CELLS!r} extra")

    def max_payload_bytes(self, kind: str) -> int | None:
        """The largest total array size this spec admits, None if unbounded.

        Extras count 4 bytes an element, the widest extra dtype (float32, uint32)."""
        sizes = [_max_elems(self.payload)] + [_max_elems(s) for s in self.extras.values()]
        if any(n is None for n in sizes):
            return None
        item = np.dtype(KIND_DTYPES[kind]).itemsize
        return sizes[0] * item + sum(sizes[1:]) * 4  # type: ignore[operator]

    def max_message_bytes(self, kind: str) -> int | None:
        """The longest encoded message (headers, ids, zlib overhead, tag) this spec can accept."""
        raw = self.max_payload_bytes(kind)
        if raw is None:
            return None
        arrays = (1 + len(self.extras)) * (1 + 0xFF + 2 + 4 * MAX_NDIM)
        return _FIXED.size + 3 * (2 + 0xFFFF) + arrays + 4 + raw + raw // 1000 + 64 + SIG_LEN


def _max_elems(spec: ShapeSpec) -> int | None:
    n = 1
    for d in spec:
        if d is None:
            return None
        n *= d.n if isinstance(d, AtMost) else d
    return n


REASONS = ("truncated", "bad_magic", "bad_version", "bad_header", "unknown_kind", "unknown_dtype",
           "unexpected_kind", "shape_mismatch", "size_mismatch", "decompress_error", "non_finite",
           "unknown_sender", "wrong_run", "unsigned", "bad_signature", "missing_extra", "unexpected_extra",
           "replayed", "bad_indices", "out_of_window", "duplicate", "foreign_space")
"""Stable rejection counter keys. missing_extra / unexpected_extra: the extras differ from the
KindSpec; replayed: a control message (v2vsim.comm.control) or a V2V message (same sender, kind and
frame) seen before; bad_indices: a "sparse" message's cells are not integers, one per payload row, in
range, strictly increasing; out_of_window: a V2V message or a world for a frame the run cannot have reached
yet (agents/ego_mailbox.py, agents/worlds.py), or an ack for a frame the driver has not published;
duplicate: a second, different message (or world) for a (sender, kind, frame) already held; size_mismatch
also a message longer than its kind's bound, refused before it is copied off the transport; foreign_space: a
message whose header names a feature space (Message.space) that the receiver's fusion models were not trained on
(KindSpec.spaces), or names none where the receiver requires one."""


class RejectedMessage(Exception):
    """A received message failed validation; `reason` is one of REASONS (a stable counter key)."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True, eq=False)
class Message:
    """One V2V message. `dtype` and `shape` describe `payload` and are derived from it."""

    kind: Kind
    run_id: str
    sender_id: str
    frame: int
    capture_time: float  # seconds in the run's clock (simulated seconds under lockstep)
    sender_pose: tuple[float, float, float, float]  # (x, y, z, yaw), world frame, as the sender knows it
    payload: np.ndarray
    compression: Compression = "none"
    channel_compression: int = 1
    extras: Mapping[str, np.ndarray] = field(default_factory=dict)
    # "<encoder>@<feature space>" of a feature map in a mixed fleet (v2vsim.perception.aligned.space_label), e.g.
    # "sinbevt@pointpillars_tiny:f487cbd52552"; "" writes none (every single-encoder run: the wire bytes of before)
    space: str = ""

    @property
    def dtype(self) -> str:
        return str(self.payload.dtype)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.payload.shape)


def encoded_size_hint(shape: Sequence[int], dtype: str = "float16") -> int:
    """Payload bytes of one uncompressed array (for budgeting; the real size is len(encode(...)))."""
    return math.prod(shape) * np.dtype(dtype).itemsize

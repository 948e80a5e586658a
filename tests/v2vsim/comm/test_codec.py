"""Wire format: exact round trips, and every malformed input rejected with its reason."""

from __future__ import annotations

import re
import struct
import tracemalloc
import zlib
from collections.abc import Sequence

import numpy as np
import pytest

from v2vsim.comm.codec import (
    REASONS,
    AtMost,
    KindSpec,
    Message,
    RejectedMessage,
    decode,
    encode,
)

RUN = "run-7"
SENDERS = {"cav1", "cav2"}


def features(seed: int = 0, shape: tuple[int, ...] = (16, 8, 8), **kw) -> Message:
    rng = np.random.default_rng(seed)
    return Message(kind="features", run_id=RUN, sender_id="cav1", frame=42, capture_time=4.2,
                   sender_pose=(10.5, -3.25, 0.0, 1.2345678901234567),
                   payload=rng.standard_normal(shape).astype(np.float32), **kw)


def points(seed: int = 0) -> Message:
    rng = np.random.default_rng(seed)
    return Message(kind="points", run_id=RUN, sender_id="cav2", frame=3, capture_time=0.3,
                   sender_pose=(1.0, 2.0, 0.0, -0.5), payload=rng.random((500, 4), dtype=np.float32) * 80)


def outputs(seed: int = 0) -> Message:
    rng = np.random.default_rng(seed)
    boxes = np.concatenate([rng.random((5, 7)) * 10, rng.random((5, 1))], axis=1).astype(np.float32)
    return Message(kind="outputs", run_id=RUN, sender_id="cav1", frame=9, capture_time=0.9,
                   sender_pose=(0.0, 0.0, 0.0, 0.0), payload=rng.random((3, 16, 16), dtype=np.float32),
                   extras={"boxes": boxes})


def reason(data: bytes, **kw) -> str:
    with pytest.raises(RejectedMessage) as ei:
        decode(data, **kw)
    assert ei.value.reason in REASONS
    return ei.value.reason


# ---- round trips -----------------------------------------------------------------------------


@pytest.mark.parametrize("compression", ["none", "zlib"])
@pytest.mark.parametrize("signed", [False, True])
def test_round_trip_features(compression: str, signed: bool) -> None:
    key = b"k" * 32 if signed else None
    msg = features(compression=compression, channel_compression=16)
    out = decode(encode(msg, key), key=key, known_senders=SENDERS, expected={"features": (16, None, 8)},
                 run_id=RUN)
    assert out.kind == "features" and out.run_id == RUN and out.sender_id == "cav1"
    assert out.frame == 42 and out.capture_time == 4.2 and out.sender_pose == msg.sender_pose
    assert out.compression == compression and out.channel_compression == 16
    assert out.dtype == "float16" and out.shape == (16, 8, 8)
    np.testing.assert_array_equal(out.payload, msg.payload.astype(np.float16))  # exact after the cast
    np.testing.assert_allclose(out.payload, msg.payload, rtol=1e-3, atol=1e-3)
    assert out.payload.flags.writeable


def test_round_trip_points_exact() -> None:
    msg = points()
    out = decode(encode(msg), expected={"points": (None, 4)})
    assert out.dtype == "float32"
    np.testing.assert_array_equal(out.payload, msg.payload)


def test_round_trip_outputs_with_boxes() -> None:
    msg = outputs()
    data = encode(msg)
    out = decode(data, expected={"outputs": (3, 16, 16), "outputs.boxes": (None, 8)})
    assert out.dtype == "float16" and set(out.extras) == {"boxes"}
    np.testing.assert_allclose(out.payload, msg.payload, atol=1e-3)
    np.testing.assert_array_equal(out.extras["boxes"], msg.extras["boxes"])


def test_unicode_ids_and_empty_points() -> None:
    msg = Message(kind="points", run_id="rün", sender_id="cav-ä", frame=0, capture_time=0.0,
                  sender_pose=(0, 0, 0, 0), payload=np.zeros((0, 4), np.float32))
    out = decode(encode(msg), known_senders={"cav-ä"})
    assert out.run_id == "rün" and out.shape == (0, 4)


def test_size_is_header_plus_float16_payload() -> None:
    data = encode(features(shape=(64, 32, 32)))
    assert 64 * 32 * 32 * 2 < len(data) < 64 * 32 * 32 * 2 + 200
    z = encode(Message(**{**features(shape=(64, 32, 32)).__dict__, "payload": np.zeros((64, 32, 32)),
                          "compression": "zlib"}))
    assert len(z) < len(data) / 20


def test_encode_refuses_non_finite_and_float16_overflow() -> None:
    bad = features()
    bad.payload[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"array payload has NaN/Inf values"):
        encode(bad)
    big = features()
    big.payload[0, 0, 0] = 1e6  # inf in float16
    with pytest.raises(ValueError, match=r"array payload has NaN/Inf values \(after the cast to float16\)"):
        encode(big)


# ---- rejections ------------------------------------------------------------------------------


def test_every_strict_prefix_is_truncated() -> None:
    for msg in (features(shape=(2, 3, 3)), features(shape=(2, 3, 3), compression="zlib")):
        data = encode(msg)
        for n in range(len(data)):
            assert reason(data[:n]) == "truncated", n


def test_bad_magic_and_version() -> None:
    data = bytearray(encode(features()))
    assert reason(b"XXXX" + bytes(data[4:])) == "bad_magic"
    data[4] = 2
    assert reason(bytes(data)) == "bad_version"


def test_unknown_kind_and_dtype() -> None:
    data = bytearray(encode(features()))
    data[5] = 9  # kind code
    assert reason(bytes(data)) == "unknown_kind"
    data = encode(features())
    # the payload array's dtype byte follows: fixed header, 2 length-prefixed ids, name length 0
    off = struct.calcsize("<4sBBBBHHIddddd") + 2 + len(RUN) + 2 + len("cav1") + 1
    assert data[off] == 1  # float16
    for code, want in ((7, "unknown_dtype"), (2, "unknown_dtype")):  # 2 = float32: wrong for features
        patched = bytearray(data)
        patched[off] = code
        assert reason(bytes(patched)) == want


def test_shape_and_size_mismatch() -> None:
    data = encode(features(shape=(16, 8, 8)))
    assert reason(data, expected={"features": (64, 8, 8)}) == "shape_mismatch"
    assert reason(data, expected={"features": (16, 8)}) == "shape_mismatch"
    assert reason(data, expected={"points": (None, 4)}) == "unexpected_kind"
    assert reason(data + b"\0") == "size_mismatch"  # trailing byte
    # header claims a different shape than the payload carries
    small = encode(features(shape=(16, 8, 4)))
    head = struct.calcsize("<4sBBBBHHIddddd") + 2 + len(RUN) + 2 + len("cav1") + 1 + 2
    assert struct.unpack_from("<3I", small, head) == (16, 8, 4)
    patched = bytearray(small)
    struct.pack_into("<3I", patched, head, 16, 8, 8)
    assert reason(bytes(patched)) in ("truncated", "size_mismatch")
    # an absurd declared size is refused before allocating
    struct.pack_into("<3I", patched, head, 0xFFFFFFFF, 0xFFFFFFFF, 8)
    assert reason(bytes(patched)) == "size_mismatch"


def test_zlib_bomb_and_garbage_are_rejected() -> None:
    msg = features(shape=(2, 2, 2), compression="zlib")
    data = encode(msg)
    body = zlib.compress(msg.payload.astype(np.float16).tobytes(), 1)
    head = data[:len(data) - len(body) - 4]
    assert head + struct.pack("<I", len(body)) + body == data
    bomb = zlib.compress(b"\0" * 10_000_000)
    assert reason(head + struct.pack("<I", len(bomb)) + bomb) == "size_mismatch"
    junk = b"not zlib at all"
    assert reason(head + struct.pack("<I", len(junk)) + junk) == "decompress_error"


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_values(value: float) -> None:
    for msg in (features(), points(), outputs()):
        arr = msg.payload.copy()
        arr.flat[3] = value
        bad = Message(**{**msg.__dict__, "payload": arr})
        assert reason(encode(bad, check_finite=False)) == "non_finite"
    boxes = outputs().extras["boxes"].copy()
    boxes[1, 2] = value
    bad = Message(**{**outputs().__dict__, "extras": {"boxes": boxes}})
    assert reason(encode(bad, check_finite=False)) == "non_finite"
    pose = Message(**{**features().__dict__, "sender_pose": (value, 0.0, 0.0, 0.0)})
    assert reason(encode(pose)) == "non_finite"


def test_unknown_sender_and_wrong_run() -> None:
    data = encode(features())
    assert reason(data, known_senders={"cav2"}) == "unknown_sender"
    assert reason(data, run_id="other-run") == "wrong_run"
    assert decode(data, known_senders=SENDERS, run_id=RUN).sender_id == "cav1"


def test_hmac_good_bad_missing() -> None:
    key = b"secret-key-0123456789"
    signed = encode(features(), key)
    assert decode(signed, key=key).frame == 42
    assert decode(signed).frame == 42  # no key configured: the tag is not checked
    assert reason(encode(features()), key=key) == "unsigned"
    assert reason(signed, key=b"another key") == "bad_signature"
    for i in (6, 30, len(signed) // 2, len(signed) - 40, len(signed) - 1):  # header, payload, tag
        flipped = bytearray(signed)
        flipped[i] ^= 0x10
        assert reason(bytes(flipped), key=key) in ("bad_signature", "bad_header"), i
    # dropping the signed flag does not sneak an unsigned message past a key holder
    stripped = bytearray(signed[:-32])
    stripped[6] &= ~0x01
    assert reason(bytes(stripped), key=key) == "unsigned"


def test_fuzz_only_rejected_message() -> None:
    rng = np.random.default_rng(1234)
    key = b"fuzz-key"
    bases = [(encode(features(shape=(4, 4, 4))), None), (encode(features(shape=(4, 4, 4), compression="zlib")), None),
             (encode(points()), None), (encode(outputs()), None), (encode(outputs(), key), key)]
    outcomes = {"ok": 0, "rejected": 0}
    for i in range(3000):
        base, k = bases[i % len(bases)]
        data = bytearray(base)
        op = rng.integers(4)
        if op == 0:  # flip a few bytes
            for j in rng.integers(0, len(data), size=rng.integers(1, 4)):
                data[j] ^= int(rng.integers(1, 256))
        elif op == 1:  # truncate
            data = data[:rng.integers(0, len(data))]
        elif op == 2:  # insert random bytes
            j = int(rng.integers(0, len(data)))
            data[j:j] = rng.bytes(int(rng.integers(1, 9)))
        else:  # random header bytes
            for j in rng.integers(0, min(80, len(data)), size=3):
                data[j] = int(rng.integers(0, 256))
        try:
            decode(bytes(data), key=k, known_senders=SENDERS, expected={"features": (4, 4, 4), "points": (None, 4),
                                                                       "outputs": (3, 16, 16)})
            outcomes["ok"] += 1
        except RejectedMessage as e:
            assert e.reason in REASONS
            assert not e.detail.startswith("internal"), e.detail  # an explicit check caught it, not the net
            outcomes["rejected"] += 1
    assert outcomes["rejected"] > 2000
    for junk in (b"", b"V2VS", b"V2VS\x01", bytes(1000), rng.bytes(5000)):
        reason(junk)


def test_outputs_with_no_boxes_and_odd_extras() -> None:
    msg = Message(kind="outputs", run_id=RUN, sender_id="cav1", frame=1, capture_time=0.1,
                  sender_pose=(0, 0, 0, 0), payload=np.zeros((2, 4, 4)),
                  extras={"boxes": np.zeros((0, 8)), "big_endian": np.arange(3, dtype=">f4")})
    out = decode(encode(msg), expected={"outputs": (2, 4, 4), "outputs.boxes": (None, 8)})
    assert out.extras["boxes"].shape == (0, 8)
    np.testing.assert_array_equal(out.extras["big_endian"], [0, 1, 2])
    with pytest.raises(ValueError, match=r"extra arrays need a non-empty name"):
        encode(Message(**{**msg.__dict__, "extras": {"": np.zeros(2)}}))


# ---- strict receiver spec (KindSpec): required extras, bounded dimensions -----------------------

SPEC = {"features": KindSpec((16, 8, 8), channel_compression=16), "points": KindSpec((AtMost(500), 4)),
        "outputs": KindSpec((3, 16, 16), extras={"boxes": (AtMost(10), 8)})}


def test_spec_accepts_what_the_senders_send() -> None:
    assert decode(encode(features(channel_compression=16)), spec=SPEC).shape == (16, 8, 8)
    assert decode(encode(points()), spec=SPEC).shape == (500, 4)
    out = decode(encode(outputs()), spec=SPEC)
    assert set(out.extras) == {"boxes"} and out.extras["boxes"].shape == (5, 8)
    empty = Message(**{**outputs().__dict__, "extras": {"boxes": np.zeros((0, 8), np.float32)}})
    assert decode(encode(empty), spec=SPEC).extras["boxes"].shape == (0, 8)


def test_outputs_without_boxes_is_missing_extra() -> None:
    """Issue 8 item 1: this message passed the codec and the ego's msg.extras["boxes"] raised KeyError."""
    bare = Message(**{**outputs().__dict__, "extras": {}})
    assert reason(encode(bare), spec=SPEC) == "missing_extra"
    assert reason(encode(bare, b"k"), key=b"k", spec=SPEC) == "missing_extra"  # a valid signature changes nothing


def test_unknown_extras_are_unexpected() -> None:
    odd = Message(**{**outputs().__dict__, "extras": {**outputs().extras, "junk": np.zeros(3, np.float32)}})
    assert reason(encode(odd), spec=SPEC) == "unexpected_extra"
    renamed = Message(**{**outputs().__dict__, "extras": {"junk": outputs().extras["boxes"]}})
    assert reason(encode(renamed), spec=SPEC) == "unexpected_extra"
    for msg in (features(channel_compression=16), points()):
        extra = Message(**{**msg.__dict__, "extras": {"boxes": np.zeros((1, 8), np.float32)}})
        assert reason(encode(extra), spec=SPEC) == "unexpected_extra"


def test_spec_bounds_and_exact_sizes() -> None:
    too_many = Message(**{**points().__dict__, "payload": np.zeros((501, 4), np.float32)})
    assert reason(encode(too_many), spec=SPEC) == "shape_mismatch"
    boxes = Message(**{**outputs().__dict__, "extras": {"boxes": np.zeros((11, 8), np.float32)}})
    assert reason(encode(boxes), spec=SPEC) == "shape_mismatch"
    wide = Message(**{**outputs().__dict__, "extras": {"boxes": np.zeros((2, 9), np.float32)}})
    assert reason(encode(wide), spec=SPEC) == "shape_mismatch"
    assert reason(encode(features(shape=(16, 8, 9), channel_compression=16)), spec=SPEC) == "shape_mismatch"
    assert reason(encode(features(channel_compression=8)), spec=SPEC) == "bad_header"  # not the ego's decoder
    assert reason(encode(points()), spec={"features": SPEC["features"]}) == "unexpected_kind"
    with pytest.raises(TypeError, match=re.escape("decode: give `spec` or `expected`, not both")):
        decode(encode(points()), spec=SPEC, expected={"points": (None, 4)})


def _points_header(n: int, body: bytes, compression: int = 1) -> bytes:
    """A points message declaring (n, 4) float32 with an arbitrary body."""
    head = struct.pack("<4sBBBBHHIddddd", b"V2VS", 1, 2, 0, compression, 1, 1, 0, 0.0, 0.0, 0.0, 0.0, 0.0)
    ids = struct.pack("<H", len(RUN)) + RUN.encode() + struct.pack("<H", 4) + b"cav1"
    arrays = struct.pack("<B", 0) + struct.pack("<BB2I", 2, 2, n, 4)
    return head + ids + arrays + struct.pack("<I", len(body)) + body


def test_zlib_bomb_declaring_67m_points_is_refused_before_inflating() -> None:
    """Issue 8 item 2: a 1 MB zlib message declaring 67 M points grew the ego by 2.3 GiB."""
    bomb = zlib.compress(b"\0" * (16 << 20), 9)  # about 16 KiB that inflate to 16 MiB
    big = _points_header(67_000_000, bomb * (1 + (1 << 20) // len(bomb)), compression=1)  # ~1 MB on the wire
    data = _points_header(67_000_000, bomb, compression=1)
    tracemalloc.start()
    try:
        assert reason(big, spec=SPEC) == "size_mismatch"  # longer than any acceptable points message
        assert reason(data, spec=SPEC) == "shape_mismatch"  # the declared shape alone gives it away
        for d in (big, data):
            assert reason(d, spec={"points": KindSpec((None, 4))}) == "size_mismatch"  # unbounded: the cap
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 4 << 20, peak
    # within the bound but inflating past the declared size: the stream decompressor stops at the cap
    small = _points_header(500, zlib.compress(b"\0" * (16 << 20), 9), compression=1)
    tracemalloc.start()
    try:
        assert reason(small, spec=SPEC) == "size_mismatch"
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 4 << 20, peak


def test_an_overlong_message_is_refused_before_hashing() -> None:
    data = encode(points(), b"k")
    padded = data[:-32] + b"\0" * (1 << 20) + data[-32:]
    assert reason(padded, key=b"k", spec=SPEC) == "size_mismatch"
    assert SPEC["points"].max_message_bytes("points") < (1 << 20)
    assert KindSpec((None, 4)).max_message_bytes("points") is None


def test_payload_array_must_be_unnamed_under_a_spec() -> None:
    data = bytearray(encode(points()))
    off = struct.calcsize("<4sBBBBHHIddddd") + 2 + len(RUN) + 2 + len("cav2")
    assert data[off] == 0  # the payload's name length
    patched = bytes(data[:off]) + b"\x01x" + bytes(data[off + 1:])
    assert reason(patched, spec=SPEC) == "bad_header"


# ---- sparse messages: integer index extras and KindSpec.cells ----------------------------------

SPARSE = {"sparse": KindSpec((AtMost(64), 4), extras={"cells": (AtMost(64),)}, cells=64)}


def sparse(cells: Sequence[int] | np.ndarray = (1, 5, 9, 63), dtype: type = np.uint16, rows: int | None = None,
           **kw) -> Message:
    """A "sparse" message of (rows, 4) values (rows: one per index unless given) and `cells`."""
    idx = np.asarray(cells, dtype=dtype)
    rng = np.random.default_rng(5)
    n = idx.shape[0] if rows is None else rows
    return Message(kind="sparse", run_id=RUN, sender_id="cav1", frame=2, capture_time=0.2,
                   sender_pose=(0, 0, 0, 0), payload=rng.standard_normal((n, 4)).astype(np.float32),
                   extras={"cells": idx}, **kw)


@pytest.mark.parametrize("dtype", [np.uint16, np.uint32])
def test_sparse_round_trip_keeps_integer_indices(dtype: type) -> None:
    for comp in ("none", "zlib"):
        msg = sparse(dtype=dtype, compression=comp)
        out = decode(encode(msg, b"k"), key=b"k", spec=SPARSE)
        assert out.kind == "sparse" and out.dtype == "float16" and out.shape == (4, 4)
        assert out.extras["cells"].dtype == dtype and out.extras["cells"].flags.writeable
        np.testing.assert_array_equal(out.extras["cells"], [1, 5, 9, 63])
    empty = decode(encode(sparse(cells=[], rows=0)), spec=SPARSE)
    assert empty.shape == (0, 4) and empty.extras["cells"].shape == (0,)


def test_encode_keeps_uint_extras_and_casts_other_dtypes_to_float32() -> None:
    big_endian = Message(**{**sparse().__dict__, "extras": {"cells": np.array([1, 2, 300], ">u2")}})
    got = decode(encode(big_endian), expected={"sparse": (None, 4)})
    assert got.extras["cells"].dtype == np.uint16 and got.extras["cells"].tolist() == [1, 2, 300]
    for dtype in (np.int64, np.int32, np.uint8, np.float64, bool):
        msg = Message(**{**sparse().__dict__, "extras": {"cells": np.array([1, 0, 1], dtype)}})
        assert decode(encode(msg), expected={"sparse": (None, 4)}).extras["cells"].dtype == np.float32, dtype


@pytest.mark.parametrize(("cells", "dtype", "rows", "why"), [
    ((1, 5, 64), np.uint16, None, "outside a grid"),  # the grid has cells 0..63
    ((1, 5, 70000), np.uint32, None, "outside a grid"),
    ((65535,), np.uint16, None, "outside a grid"),
    ((1, 9, 5), np.uint16, None, "not strictly increasing"),
    ((1, 5, 5, 9), np.uint16, None, "not strictly increasing"),  # a duplicate
    ((0, 0), np.uint32, None, "not strictly increasing"),
    ((9, 5, 1), np.uint16, None, "not strictly increasing"),
    ((1, 5, 9), np.uint16, 4, "payload rows"),  # one index short
    ((1, 5, 9), np.uint16, 2, "payload rows"),  # one index too many
    ((), np.uint16, 1, "payload rows"),
    ((1, 5, 9), np.float16, None, "dtype float16"),
    ((1, 5, 9), np.float32, None, "dtype float32"),
    ((), np.float32, 0, "dtype float32"),  # no indices, but of the wrong kind
])
def test_bad_indices(cells: tuple[int, ...], dtype: type, rows: int | None, why: str) -> None:
    data = encode(sparse(cells, dtype, rows))
    with pytest.raises(RejectedMessage) as ei:
        decode(data, spec=SPARSE)
    assert ei.value.reason == "bad_indices" and why in ei.value.detail, ei.value
    assert reason(encode(sparse(cells, dtype, rows), b"k"), key=b"k", spec=SPARSE) == "bad_indices"
    decode(data, expected={"sparse": (None, 4)})  # the lax form checks no indices: it scatters nothing


def test_sparse_extras_missing_unexpected_or_misshapen() -> None:
    assert reason(encode(Message(**{**sparse().__dict__, "extras": {}})), spec=SPARSE) == "missing_extra"
    renamed = Message(**{**sparse().__dict__, "extras": {"cell": sparse().extras["cells"]}})
    assert reason(encode(renamed), spec=SPARSE) == "unexpected_extra"
    two_d = Message(**{**sparse().__dict__, "extras": {"cells": np.array([[1, 5, 9, 63]], np.uint16)}})
    assert reason(encode(two_d), spec=SPARSE) == "shape_mismatch"
    assert reason(encode(sparse(cells=np.arange(65), rows=65)), spec=SPARSE) == "shape_mismatch"
    assert reason(encode(sparse(channel_compression=2)), spec=SPARSE) == "bad_header"


def test_integer_extras_only_as_cells() -> None:
    """Under a spec an integer array is accepted only where it is checked as indices."""
    int_boxes = Message(**{**outputs().__dict__, "extras": {"boxes": np.zeros((2, 8), np.uint16)}})
    assert reason(encode(int_boxes), spec=SPEC) == "unknown_dtype"
    assert decode(encode(int_boxes), expected={"outputs": (3, 16, 16)}).extras["boxes"].dtype == np.uint16
    no_cells_spec = {"sparse": KindSpec((AtMost(64), 4), extras={"cells": (AtMost(64),)})}
    assert reason(encode(sparse()), spec=no_cells_spec) == "unknown_dtype"
    # the sparse payload itself is float16, whatever the extras
    data = bytearray(encode(sparse()))
    off = struct.calcsize("<4sBBBBHHIddddd") + 2 + len(RUN) + 2 + len("cav1") + 1
    assert data[off] == 1
    data[off] = 3  # uint16: the same size, so only the dtype rule refuses it
    assert reason(bytes(data), spec=SPARSE) == "unknown_dtype"


def test_evidence_travels_as_bytes_and_nothing_else_is_bytes() -> None:
    """A sender's packed free-space evidence (uint8) beside its map: optional, sized, and the only uint8 extra."""
    ev = np.arange(32, dtype=np.uint8)
    spec = {"features": KindSpec((16, 8, 8), extras={"evidence": (32,)}, optional=frozenset({"evidence"}))}
    got = decode(encode(features(extras={"evidence": ev})), spec=spec)
    assert got.extras["evidence"].dtype == np.uint8 and np.array_equal(got.extras["evidence"], ev)
    assert decode(encode(features()), spec=spec).extras == {}  # optional
    assert reason(encode(features(extras={"evidence": ev[:31]})), spec=spec) == "shape_mismatch"
    as_bytes = {"features": KindSpec((16, 8, 8), extras={"evidencX": (32,)}, optional=frozenset({"evidencX"}))}
    assert decode(encode(features(extras={"evidencX": ev})), spec=as_bytes).extras["evidencX"].dtype == np.float32
    forged = encode(features(extras={"evidence": ev})).replace(b"evidence", b"evidencX")  # bytes by another name
    assert reason(forged, spec=as_bytes) == "unknown_dtype"


def test_kindspec_cells_needs_a_required_cells_extra() -> None:
    needs = re.escape("KindSpec(cells=4) needs cells >= 1 and a required 'cells' extra")
    for bad in (dict(extras={}), dict(extras={"cells": (AtMost(4),)}, optional=frozenset({"cells"})),
                dict(extras={"idx": (AtMost(4),)})):
        with pytest.raises(ValueError, match=needs):
            KindSpec((AtMost(4), 2), cells=4, **bad)
    with pytest.raises(ValueError, match=re.escape("KindSpec(cells=0) needs cells >= 1")):
        KindSpec((AtMost(4), 2), extras={"cells": (AtMost(4),)}, cells=0)


def test_max_payload_bytes_bounds_uint32_cells() -> None:
    spec = SPARSE["sparse"]
    full = sparse(np.arange(64), np.uint32)
    body = full.payload.astype(np.float16).nbytes + full.extras["cells"].nbytes
    assert body == spec.max_payload_bytes("sparse") == 64 * 4 * 2 + 64 * 4
    assert len(encode(full, b"k")) <= spec.max_message_bytes("sparse")
    assert decode(encode(full), spec=SPARSE).shape == (64, 4)

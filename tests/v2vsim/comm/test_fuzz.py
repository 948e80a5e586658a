"""Fuzzing the ego's own decode path (v2vsim.comm.wire_spec.EgoDecoder, which agents/ego.py calls
for every received message): over 10,000 seeded malformed messages of every kind, each one must be
rejected with a reason from REASONS and counted, nothing else may escape, and memory stays bounded
(issue 8: an outputs message without boxes killed the ego; a 1 MB zlib bomb declaring 67 M points
grew it by 2.3 GiB). Sparse messages also get their cell indices corrupted (`bad_cells`): the ego
scatters the payload with them, so a bad index must be 'bad_indices', never an IndexError.

The scenario is the shipped intersection with a small LiDAR (4 x 64 rays) and small encoder dims,
so that every message is a few KiB and the whole run takes a few seconds on a laptop core.
"""

from __future__ import annotations

import hashlib
import hmac
import inspect
import struct
import time
import tracemalloc
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from v2vsim.comm.codec import (
    CELLS,
    FLAG_SIGNED,
    KIND_CODES,
    REASONS,
    TAG_LEN,
    AtMost,
    Message,
    RejectedMessage,
    encode,
)
from v2vsim.comm.sparse import index_dtype
from v2vsim.comm.stats import CommStats
from v2vsim.comm.wire_spec import KEY_KINDS, MAX_BOXES, EgoDecoder, ego_wire_spec
from v2vsim.config import Scenario, load_scenario

REPO = Path(__file__).resolve().parents[3]
RUN = "fuzz-run"
SENDERS = frozenset({"cav0", "cav1", "cav2"})
KEY = b"fuzz key 0123456789"
C, F, RATIO = 16, 8, 4  # encoder channels and cells, comm.channel_compression: features (4, 8, 8)
S = 256  # late outputs' maps: the heads' segmentation grid (the preset's seg_cells), whatever F
KINDS = list(KIND_CODES)
FIXED = struct.Struct("<4sBBBBHHIddddd")
FRAME_AND_POSE = range(12, FIXED.size)  # frame, capture time, pose: any value of these is legitimate
MIN_CASES = 10_000


def small_scenario() -> Scenario:
    return load_scenario(REPO / "scenarios" / "intersection.yaml",
                         ["sensors.lidar.channels=4", "sensors.lidar.points_per_channel=64",
                          f"comm.channel_compression={RATIO}"])


@dataclass(frozen=True)
class Case:
    what: str
    kind: str  # the kind of the key it arrived on
    sender: str  # the sender chunk of the key it arrived on
    data: bytes
    keyed: bool  # decoded by the ego of a comm.auth run


def _msg(kind: str, rng: np.random.Generator, *, sender: str = "cav1", compression: str = "none",
         run_id: str = RUN, zeros: bool = False, n: int | None = None, **kw) -> Message:
    """A valid message of `kind` as the scenario's CAVs send it (random or all-zero values);
    `n`: the points, boxes or sparse cells it carries."""
    def fill(shape: tuple[int, ...]) -> np.ndarray:
        return np.zeros(shape, np.float32) if zeros else rng.random(shape, dtype=np.float32)

    stamp = dict(run_id=run_id, sender_id=sender, frame=int(rng.integers(0, 400)), capture_time=0.1,
                 sender_pose=(1.0, 2.0, 0.0, 0.5), compression=compression)
    if kind == "features":
        return Message(kind="features", payload=fill((C // RATIO, F, F)), channel_compression=RATIO,
                       **{**stamp, **kw})
    if kind == "points":
        return Message(kind="points", payload=fill((20 if n is None else n, 4)), **{**stamp, **kw})
    if kind == "sparse":
        k = 20 if n is None else n
        cells = np.sort(rng.choice(F * F, size=k, replace=False)).astype(index_dtype(F * F))
        return Message(kind="sparse", payload=fill((k, C // RATIO)), extras={CELLS: cells},
                       channel_compression=RATIO, **{**stamp, **kw})
    boxes = fill((3 if n is None else n, 6))
    return Message(kind="outputs", payload=fill((3, S, S)), extras={"boxes": boxes}, **{**stamp, **kw})


def _sign(unsigned: bytes, key: bytes = KEY) -> bytes:
    """Set the signed flag on an unsigned message and append a valid tag (a key holder's forgery)."""
    data = bytearray(unsigned)
    data[6] |= FLAG_SIGNED
    return bytes(data) + hmac.new(key, bytes(data), hashlib.sha256).digest()


def _unsigned(data: bytes, keyed: bool) -> bytes:
    """What the attacker patches: the unsigned form (re-signed by _out when the target is keyed)."""
    return data[:-TAG_LEN] if keyed else data


def _out(data: bytes, keyed: bool) -> bytes:
    return _sign(data) if keyed else data


def _layout(data: bytes) -> dict[str, int]:
    """Offsets in an unsigned message: after the ids, each array header, the body length."""
    pos = FIXED.size
    for _ in range(2):
        (n,) = struct.unpack_from("<H", data, pos)
        pos += 2 + n
    out = {"arrays": pos}
    (n_arrays,) = struct.unpack_from("<H", data, 10)
    for i in range(n_arrays):
        out[f"name{i}"] = pos
        pos += 1 + data[pos]
        out[f"dtype{i}"] = pos
        ndim = data[pos + 1]
        out[f"shape{i}"] = pos + 2
        out[f"ndim{i}"] = ndim
        pos += 2 + 4 * ndim
    out["body_len"] = pos
    out["body"] = pos + 4
    return out


@cache
def _bomb() -> bytes:
    """~16 KiB of zlib that inflate to 16 MiB of zeros."""
    return zlib.compress(b"\0" * (16 << 20), 9)


def random_bytes(rng: np.random.Generator) -> Iterator[Case]:
    kinds = KINDS
    for i in range(1500):
        kind = kinds[i % len(kinds)]
        yield Case("random", kind, "cav1", rng.bytes(int(rng.integers(0, 400))), bool(i % 2))
    for i in range(600):  # past the magic and version check, random thereafter
        kind = kinds[i % len(kinds)]
        data = b"V2VS\x01" + bytes([KIND_CODES[kind]]) + rng.bytes(int(rng.integers(0, 300)))
        yield Case("random after the magic", kind, "cav1", data, bool(i % 2))


def truncations(rng: np.random.Generator) -> Iterator[Case]:
    bases = [_msg("features", rng), _msg("features", rng, compression="zlib"), _msg("points", rng),
             _msg("outputs", rng, compression="zlib", zeros=True), _msg("sparse", rng, n=6)]
    for msg in bases:
        for keyed in (False, True):
            data = encode(msg, KEY if keyed else None)
            for n in range(len(data)):
                yield Case(f"{msg.kind} truncated at {n}", msg.kind, "cav1", data[:n], keyed)


def bit_flips(rng: np.random.Generator) -> Iterator[Case]:
    for kind in KIND_CODES:
        msg = _msg(kind, rng, compression="zlib" if kind == "outputs" else "none", zeros=kind == "outputs")
        plain = encode(msg)
        lay = _layout(plain)
        for byte in range(lay["body"]):  # every header bit whose every change must be refused
            if byte in FRAME_AND_POSE:
                continue
            for bit in range(8):
                data = bytearray(plain)
                data[byte] ^= 1 << bit
                yield Case(f"{kind} header bit {byte}.{bit}", kind, "cav1", bytes(data), False)
        signed = encode(msg, KEY)
        for _ in range(500):  # under a key every bit of the message counts, payload and tag included
            data = bytearray(signed)
            data[int(rng.integers(0, len(data)))] ^= 1 << int(rng.integers(0, 8))
            yield Case(f"{kind} signed bit flip", kind, "cav1", bytes(data), True)


def _array_to_corrupt(i: int, rng: np.random.Generator) -> tuple[str, bool, bytearray, dict[str, int], int]:
    """Case i's kind (cycling), whether it is keyed (alternating), a valid message as editable bytes
    (unsigned: `_out` signs it again after the edit), its header layout, and which array to corrupt."""
    kind = KINDS[i % len(KINDS)]
    keyed = bool(i % 2)
    data = bytearray(_unsigned(encode(_msg(kind, rng), KEY if keyed else None), keyed))
    return kind, keyed, data, _layout(bytes(data)), int(rng.integers(0, 2 if kind in ("outputs", "sparse") else 1))


def huge_shapes(rng: np.random.Generator) -> Iterator[Case]:
    for i in range(600):
        kind, keyed, data, lay, arr = _array_to_corrupt(i, rng)
        for d in range(lay[f"ndim{arr}"]):
            big = int(rng.choice([1 << 20, 67_000_000, 0xFFFFFFFF, int(rng.integers(257, 1 << 32))]))
            struct.pack_into("<I", data, lay[f"shape{arr}"] + 4 * d, big)
        yield Case(f"{kind} array {arr} declared huge", kind, "cav1", _out(bytes(data), keyed), keyed)


def zlib_bombs(rng: np.random.Generator) -> Iterator[Case]:
    bomb = _bomb()
    big_bomb = bomb * (1 + (1 << 20) // len(bomb))  # ~1 MB on the wire
    for keyed in (False, True):
        for kind in KIND_CODES:
            msg = _msg(kind, rng, compression="zlib", zeros=True)
            plain = _unsigned(encode(msg, KEY if keyed else None), keyed)
            lay = _layout(plain)
            head = plain[:lay["body_len"]]
            for body in (bomb, big_bomb):
                yield Case(f"{kind} zlib bomb", kind, "cav1", _out(head + struct.pack("<I", len(body)) + body, keyed),
                           keyed)
            if kind == "points":  # the issue's message: 67 M points declared
                for n in (67_000_000, 256, 257):
                    patched = bytearray(head)
                    struct.pack_into("<I", patched, lay["shape0"], n)
                    for body in (bomb, big_bomb):
                        data = bytes(patched) + struct.pack("<I", len(body)) + body
                        yield Case(f"points ({n}, 4) zlib bomb", kind, "cav1", _out(data, keyed), keyed)
        # an unknown extra of 1 GiB declared, its body a bomb
        msg = _msg("outputs", rng, compression="zlib", zeros=True)
        msg = Message(**{**msg.__dict__, "extras": {**msg.extras, "junk": np.zeros((2, 2), np.float32)}})
        plain = _unsigned(encode(msg, KEY if keyed else None), keyed)
        lay = _layout(plain)
        patched = bytearray(plain[:lay["body_len"]])
        struct.pack_into("<2I", patched, lay["shape2"], 1 << 14, 1 << 14)
        data = bytes(patched) + struct.pack("<I", len(big_bomb)) + big_bomb
        yield Case("outputs with a 1 GiB unknown extra", "outputs", "cav1", _out(data, keyed), keyed)


def non_finite(rng: np.random.Generator) -> Iterator[Case]:
    for i in range(900):
        kind = KINDS[i % len(KINDS)]
        keyed = bool(i % 2)
        msg = _msg(kind, rng, compression="zlib" if i % 5 == 0 else "none")
        value = [np.nan, np.inf, -np.inf, 1e6 if kind != "points" else np.nan][i % 4]  # 1e6: inf in float16
        where = int(rng.integers(0, 3))
        if where == 0 or (where == 1 and kind != "outputs"):  # sparse cells are integers: always finite
            payload = msg.payload.copy()
            payload.flat[int(rng.integers(0, payload.size))] = value
            msg = Message(**{**msg.__dict__, "payload": payload})
        elif where == 1:
            boxes = msg.extras["boxes"].copy()
            boxes.flat[int(rng.integers(0, boxes.size))] = value if value != 1e6 else np.nan  # float32 boxes
            msg = Message(**{**msg.__dict__, "extras": {"boxes": boxes}})
        else:
            pose = list(msg.sender_pose)
            pose[int(rng.integers(0, 4))] = value if not np.isfinite(value) else np.nan
            msg = Message(**{**msg.__dict__, "sender_pose": tuple(pose)})
        with np.errstate(over="ignore"):
            data = encode(msg, KEY if keyed else None, check_finite=False)
        yield Case(f"{kind} non-finite", kind, "cav1", data, keyed)


def wrong_dtypes(rng: np.random.Generator) -> Iterator[Case]:
    for i in range(450):
        kind, keyed, plain, lay, arr = _array_to_corrupt(i, rng)
        right = plain[lay[f"dtype{arr}"]]
        # boxes may be float16 or float32; any other change (integer boxes, float cells) is refused
        choices = [c for c in range(256) if c != right and not (kind == "outputs" and arr == 1 and c in (1, 2))]
        plain[lay[f"dtype{arr}"]] = int(rng.choice(choices[:8] if i % 3 else choices))
        yield Case(f"{kind} array {arr} dtype", kind, "cav1", _out(bytes(plain), keyed), keyed)


def tampered_signatures(rng: np.random.Generator) -> Iterator[Case]:
    for kind in KIND_CODES:
        msg = _msg(kind, rng, compression="zlib", zeros=True)
        signed = encode(msg, KEY)
        for i in range(TAG_LEN * 8):  # every bit of the tag
            data = bytearray(signed)
            data[len(data) - TAG_LEN + i // 8] ^= 1 << (i % 8)
            yield Case(f"{kind} tag bit {i}", kind, "cav1", bytes(data), True)
        for _ in range(40):
            yield Case(f"{kind} random tag", kind, "cav1", signed[:-TAG_LEN] + rng.bytes(TAG_LEN), True)
            yield Case(f"{kind} other key", kind, "cav1", encode(msg, rng.bytes(16)), True)
        stripped = bytearray(signed[:-TAG_LEN])
        stripped[6] &= ~FLAG_SIGNED
        yield Case(f"{kind} signature stripped", kind, "cav1", bytes(stripped), True)
        yield Case(f"{kind} unsigned", kind, "cav1", encode(msg), True)
        yield Case(f"{kind} flag without tag", kind, "cav1", _sign(encode(msg))[:-TAG_LEN], True)
        other_run = Message(**{**msg.__dict__, "run_id": "another-run"})
        yield Case(f"{kind} signed for another run", kind, "cav1", encode(other_run, KEY), True)
        stranger = Message(**{**msg.__dict__, "sender_id": "cav9"})
        yield Case(f"{kind} signed by an unknown sender", kind, "cav9", encode(stranger, KEY), True)


def extras(rng: np.random.Generator) -> Iterator[Case]:
    junk_shapes = [(1,), (2, 2), (0,), (MAX_BOXES, 6), (7, 7, 7)]
    for i in range(200):
        keyed = bool(i % 2)
        key = KEY if keyed else None
        outputs = _msg("outputs", rng, compression="zlib" if i % 4 == 0 else "none")
        boxes = outputs.extras["boxes"]
        junk = np.zeros(junk_shapes[i % len(junk_shapes)], np.float32)
        name = ["junk", "Boxes", "boxes ", "b", "x" * 255][i % 5]
        cases = {
            "outputs without boxes": Message(**{**outputs.__dict__, "extras": {}}),
            "outputs with an unknown extra": Message(**{**outputs.__dict__, "extras": {"boxes": boxes, name: junk}}),
            "outputs with only an unknown extra": Message(**{**outputs.__dict__, "extras": {name: boxes}}),
            "outputs with too many boxes": Message(**{**outputs.__dict__, "extras": {
                "boxes": np.zeros((MAX_BOXES + 1 + i, 6), np.float32)}}),
            "outputs with 8-wide boxes": Message(**{**outputs.__dict__, "extras": {"boxes": np.zeros((2, 8))}}),
        }
        for kind in ("features", "points"):
            msg = _msg(kind, rng)
            cases[f"{kind} with boxes"] = Message(**{**msg.__dict__, "extras": {"boxes": boxes}})
        sparse = _msg("sparse", rng, compression="zlib" if i % 4 == 0 else "none")
        cells = sparse.extras[CELLS]
        cases.update({
            "sparse without cells": Message(**{**sparse.__dict__, "extras": {}}),
            "sparse with cells and boxes": Message(**{**sparse.__dict__, "extras": {CELLS: cells, "boxes": boxes}}),
            "sparse with cells under another name": Message(**{**sparse.__dict__, "extras": {name: cells}}),
            "outputs with cells": Message(**{**outputs.__dict__, "extras": {"boxes": boxes, CELLS: cells}}),
            "features with cells": Message(**{**_msg("features", rng).__dict__, "extras": {CELLS: cells}}),
        })
        for what, msg in cases.items():
            yield Case(what, msg.kind, "cav1", encode(msg, key), keyed)
        # the same extra twice (encode cannot: patch a 5-letter name into "boxes")
        dup = Message(**{**outputs.__dict__, "extras": {"boxes": boxes, "boxez": boxes}})
        data = bytearray(_unsigned(encode(dup, key), keyed))
        lay = _layout(bytes(data))
        data[lay["name2"] + 1:lay["name2"] + 6] = b"boxes"
        yield Case("outputs with boxes twice", "outputs", "cav1", _out(bytes(data), keyed), keyed)


def misrouted(rng: np.random.Generator) -> Iterator[Case]:
    kinds = KINDS
    for i in range(300):
        keyed = bool(i % 2)
        key = KEY if keyed else None
        kind = kinds[i % len(kinds)]
        other = kinds[(i + 1 + (i // len(kinds)) % (len(kinds) - 1)) % len(kinds)]  # every other kind in turn
        msg = _msg(kind, rng)
        data = encode(msg, key)
        if kind not in KEY_KINDS.get(other, (other,)):  # sparse rides the features key by design
            yield Case(f"{kind} on the {other} key", other, "cav1", data, keyed)
        yield Case(f"{kind} on the vis key", "vis", "cav1", data, keyed)
        yield Case(f"{kind} from cav1 under cav2's key", kind, "cav2", data, keyed)
        yield Case(f"{kind} of another run", kind, "cav1", encode(_msg(kind, rng, run_id="old-run"), key), keyed)
        yield Case(f"{kind} from an unknown sender", kind, "cav7", encode(_msg(kind, rng, sender="cav7"), key), keyed)
    for i in range(100):
        keyed = bool(i % 2)
        key = KEY if keyed else None
        feats = Message(**{**_msg("features", rng).__dict__, "channel_compression": [1, 2, 8, 64][i % 4]})
        yield Case("features of another channel compression", "features", "cav1", encode(feats, key), keyed)
        wrong = Message(**{**_msg("features", rng).__dict__, "payload": np.zeros((C, F, F), np.float32)})
        yield Case("uncompressed features", "features", "cav1", encode(wrong, key), keyed)
        pts = _msg("points", rng, n=4 * 64 + 1 + i)
        yield Case("one sweep and more", "points", "cav1", encode(pts, key), keyed)
        other = Message(**{**_msg("points", rng).__dict__, "payload": np.zeros((5, 3 + 2 * (i % 2)), np.float32)})
        yield Case("points of 3 or 5 fields", "points", "cav1", encode(other, key), keyed)
        maps = Message(**{**_msg("outputs", rng).__dict__, "payload": np.zeros((3, S, S + 1))})
        yield Case("outputs of another grid", "outputs", "cav1", encode(maps, key), keyed)
        sparse = Message(**{**_msg("sparse", rng).__dict__, "channel_compression": [1, 2, 8, 64][i % 4]})
        yield Case("sparse of another channel compression", "sparse", "cav1", encode(sparse, key), keyed)
        wide = _msg("sparse", rng)
        wide = Message(**{**wide.__dict__, "payload": np.zeros((wide.shape[0], C), np.float32)})
        yield Case("uncompressed sparse", "sparse", "cav1", encode(wide, key), keyed)
        every = _msg("sparse", rng, n=F * F)
        more = Message(**{**every.__dict__, "payload": np.zeros((F * F + 1 + i, C // RATIO), np.float32),
                          "extras": {CELLS: np.arange(F * F + 1 + i, dtype=np.uint16)}})
        yield Case("sparse of more cells than the grid", "sparse", "cav1", encode(more, key), keyed)


def bad_cells(rng: np.random.Generator) -> Iterator[Case]:
    """Sparse messages whose indices the ego could not scatter with: each one is 'bad_indices'
    (or, for a shape the spec already bounds, 'shape_mismatch')."""
    dtype = index_dtype(F * F)
    for i in range(400):
        keyed = bool(i % 2)
        key = KEY if keyed else None
        msg = _msg("sparse", rng, n=int(rng.integers(2, F * F)), compression="zlib" if i % 3 == 0 else "none")
        cells = msg.extras[CELLS].astype(np.int64)
        j = int(rng.integers(0, cells.size))
        what = ["out of range", "last out of range", "swapped", "duplicate", "reversed", "one short", "one more",
                "float16", "float32", "2-D", "uint32 out of range", "max"][i % 12]
        if what == "out of range":
            cells[j] = int(rng.integers(F * F, 1 << 16))
        elif what == "last out of range":
            cells[-1] = F * F
        elif what == "swapped":
            cells[[j, (j + 1) % cells.size]] = cells[[(j + 1) % cells.size, j]]
        elif what == "duplicate":
            cells[j] = cells[j - 1] if j else cells[1]
        elif what == "reversed":
            cells = cells[::-1]
        elif what == "one short":
            cells = np.delete(cells, j)
        elif what == "one more":
            spare = np.setdiff1d(np.arange(F * F), cells)
            cells = np.sort(np.append(cells, spare[int(rng.integers(0, spare.size))]))
        elif what == "max":
            cells[j] = np.iinfo(dtype).max
        out_dtype = {"float16": np.float16, "float32": np.float32, "2-D": dtype,
                     "uint32 out of range": np.uint32}.get(what, dtype)
        if what == "2-D":
            cells = cells.reshape(1, -1)
        if what == "uint32 out of range":
            cells[j] = int(rng.integers(1 << 16, 1 << 32))
        bad = Message(**{**msg.__dict__, "extras": {CELLS: cells.astype(out_dtype)}})
        yield Case(f"sparse cells {what}", "sparse", "cav1", encode(bad, key), keyed)


GENERATORS: list[Callable[[np.random.Generator], Iterator[Case]]] = [
    random_bytes, truncations, bit_flips, huge_shapes, zlib_bombs, non_finite, wrong_dtypes, tampered_signatures,
    extras, misrouted, bad_cells]


def test_the_wire_spec_is_the_scenarios() -> None:
    sc = load_scenario(REPO / "scenarios" / "intersection.yaml")
    spec = ego_wire_spec(sc, 64, 32)
    assert spec["features"].payload == (64, 32, 32) and spec["features"].channel_compression == 1
    assert spec["points"].payload == (AtMost(32 * 1024), 4)
    assert spec["outputs"].payload == (3, 256, 256) and dict(spec["outputs"].extras) == {"boxes": (AtMost(100), 6)}
    assert spec["outputs"].optional == frozenset()
    assert spec["sparse"].payload == (AtMost(1024), 64) and dict(spec["sparse"].extras) == {CELLS: (AtMost(1024),)}
    assert spec["sparse"].cells == 1024 and spec["sparse"].channel_compression == 1
    assert spec["sparse"].max_payload_bytes("sparse") == 1024 * 64 * 2 + 1024 * 4
    small = ego_wire_spec(small_scenario(), C, F)["sparse"]
    assert small.payload == (AtMost(F * F), C // RATIO) and small.channel_compression == RATIO
    # every bound is finite: nothing the ego accepts can be larger than this
    assert all(s.max_payload_bytes(k) is not None for k, s in spec.items())
    assert spec["points"].max_payload_bytes("points") == 32 * 1024 * 4 * 4
    from models.heads import decode_detections

    assert inspect.signature(decode_detections).parameters["top_k"].default == MAX_BOXES


def test_valid_messages_pass_the_ego_decoder() -> None:
    """The control for the fuzz below: what the CAVs send is accepted, so rejections mean something."""
    rng = np.random.default_rng(7)
    spec = ego_wire_spec(small_scenario(), C, F)
    for key in (None, KEY):
        dec = EgoDecoder(spec, RUN, SENDERS, key)
        stats = CommStats()
        for kind in KIND_CODES:
            for comp in ("none", "zlib"):
                for n in (0, 1, {"points": 256, "sparse": F * F}.get(kind, MAX_BOXES)):
                    msg = _msg(kind, rng, compression=comp, n=n)
                    got = dec.receive(kind, encode(msg, key), "cav1", [stats])
                    assert got is not None and got.kind == kind, (kind, comp, n)
            # the cells may also come as uint32, whatever the grid
            msg = _msg("sparse", rng, compression=comp)
            wide = Message(**{**msg.__dict__, "extras": {CELLS: msg.extras[CELLS].astype(np.uint32)}})
            got = dec.receive("sparse", encode(wide, key), "cav1", [stats])
            assert got is not None and got.extras[CELLS].dtype == np.uint32
            np.testing.assert_array_equal(got.extras[CELLS], msg.extras[CELLS])
        assert stats.rejected == 0


def test_fuzz_every_malformed_message_is_rejected_and_counted() -> None:
    rng = np.random.default_rng(20240508)
    spec = ego_wire_spec(small_scenario(), C, F)
    decoders = {False: EgoDecoder(spec, RUN, SENDERS, None), True: EgoDecoder(spec, RUN, SENDERS, KEY)}
    stats = CommStats()
    n = 0
    by_generator: dict[str, int] = {}
    peak = 0
    t0 = time.perf_counter()
    for gen in GENERATORS:
        cases = list(gen(rng))
        for case in cases:
            dec = decoders[case.keyed]
            try:
                dec.decode(case.kind, case.data, case.sender)
            except RejectedMessage as e:
                assert e.reason in REASONS, (case.what, e.reason)
                assert not e.detail.startswith("internal"), (case.what, e.detail)  # a check caught it
            else:
                pytest.fail(f"accepted: {case.what}")
            # the ego's own call: counted, never raised
            assert dec.receive(case.kind, case.data, case.sender, [stats]) is None, case.what
        # Memory, under tracemalloc (15x slower, hence a sample; the cases were made outside the
        # trace, so only the decoder's own allocations count): every bomb, one in 20 of the rest.
        traced = cases if gen is zlib_bombs else cases[::20]
        tracemalloc.start()
        try:
            for case in traced:
                decoders[case.keyed].receive(case.kind, case.data, case.sender, [CommStats()])
            peak = max(peak, tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
        n += len(cases)
        by_generator[gen.__name__] = len(cases)
    elapsed = time.perf_counter() - t0
    assert n >= MIN_CASES, by_generator
    assert all(v >= 20 for v in by_generator.values()), by_generator
    assert stats.rejected == n
    assert set(stats.rejected_reasons) <= set(REASONS)
    for must in ("truncated", "bad_magic", "bad_signature", "unsigned", "shape_mismatch", "size_mismatch",
                 "non_finite", "unknown_dtype", "missing_extra", "unexpected_extra", "unexpected_kind",
                 "unknown_sender", "wrong_run", "decompress_error", "bad_header", "bad_indices"):
        assert stats.rejected_reasons[must] > 0, (must, dict(stats.rejected_reasons))
    assert peak < 64 << 20, f"tracemalloc peak {peak / 2**20:.1f} MiB"
    print(f"fuzz: {n} messages in {elapsed:.2f} s, tracemalloc peak {peak / 2**20:.2f} MiB, "
          f"{dict(stats.rejected_reasons)}")


def test_bad_cells_are_bad_indices() -> None:
    """The fuzz above only asks for some reason; each corrupted index set must be refused as such."""
    spec = ego_wire_spec(small_scenario(), C, F)
    decoders = {False: EgoDecoder(spec, RUN, SENDERS, None), True: EgoDecoder(spec, RUN, SENDERS, KEY)}
    seen = set()
    for case in bad_cells(np.random.default_rng(3)):
        with pytest.raises(RejectedMessage) as ei:
            decoders[case.keyed].decode(case.kind, case.data, case.sender)
        want = "shape_mismatch" if case.what.endswith("2-D") else "bad_indices"
        assert ei.value.reason == want, (case.what, ei.value)
        seen.add(case.what)
    assert len(seen) == 12


def test_the_issues_zlib_bomb_allocates_nothing() -> None:
    """1 MB of zlib declaring 67 M points (what grew the ego by 2.3 GiB): refused from the header."""
    dec = EgoDecoder(ego_wire_spec(load_scenario(REPO / "scenarios" / "intersection.yaml"), 64, 32), RUN, SENDERS)
    bomb = _bomb()
    rng = np.random.default_rng(0)
    plain = encode(_msg("points", rng, compression="zlib", zeros=True))
    lay = _layout(plain)
    for body in (bomb, bomb * (1 + (1 << 20) // len(bomb))):
        head = bytearray(plain[:lay["body_len"]])
        struct.pack_into("<I", head, lay["shape0"], 67_000_000)
        data = bytes(head) + struct.pack("<I", len(body)) + body
        stats = CommStats()
        tracemalloc.start()
        try:
            assert dec.receive("points", data, "cav1", [stats]) is None
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert stats.rejected_reasons.keys() <= {"shape_mismatch", "size_mismatch"} and stats.rejected == 1
        assert peak < 256 << 10, peak  # not even a copy of the message


def test_the_features_key_takes_sparse_messages_and_bounds_both() -> None:
    """Under comm.share topk a CAV's features come as "sparse" on the features key: accepted there, and the
    key's size limit is the larger of the two kinds' (a dense map is the larger)."""
    from v2vsim.comm.share import dense_payload, feature_message
    from v2vsim.config import load_scenario

    sc = load_scenario("scenarios/intersection.yaml")
    dec = EgoDecoder(ego_wire_spec(sc, 64, 32), "run", frozenset({"cav0", "cav1"}))
    rng = np.random.default_rng(0)
    payload = rng.standard_normal((64, 32, 32)).astype(np.float16)
    confidence = rng.uniform(size=(32, 32))
    stamp = {"run_id": "run", "sender_id": "cav1", "frame": 3, "capture_time": 0.3, "sender_pose": (1, 2, 0, 0.5)}
    sparse = feature_message(payload, confidence, 0.25, stamp)
    dense = feature_message(payload, confidence, 1.0, stamp)
    assert (sparse.kind, dense.kind) == ("sparse", "features")
    got = dec.decode("features", encode(sparse), "cav1")
    restored = dense_payload(got, (64, 32, 32))
    sent = np.zeros(32 * 32, bool)
    sent[sparse.extras["cells"]] = True
    assert sent.sum() == 256 and np.array_equal(restored.reshape(64, -1)[:, sent], payload.reshape(64, -1)[:, sent])
    assert not restored.reshape(64, -1)[:, ~sent].any()
    assert dec.max_bytes("features") >= len(encode(dense)) > len(encode(sparse))
    with pytest.raises(RejectedMessage, match="unexpected_kind"):
        dec.decode("points", encode(sparse), "cav1")

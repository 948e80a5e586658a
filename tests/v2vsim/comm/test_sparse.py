"""Sparse BEV features: cell selection, gather/scatter, the "sparse" message through the ego's
decoder, and the size rule that picks it over the dense "features" message."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from v2vsim.comm.codec import CELLS, Message, RejectedMessage, encode
from v2vsim.comm.sparse import (
    dense_wire_bytes,
    gather,
    index_dtype,
    scatter,
    select_cells,
    sparse_is_smaller,
    sparse_wire_bytes,
)
from v2vsim.comm.wire_spec import EgoDecoder, ego_wire_spec
from v2vsim.config import load_scenario

REPO = Path(__file__).resolve().parents[3]
RUN = "sparse-run"
KEY = b"sparse key"
C, F = 64, 32  # the shipped encoder's output: 64 channels on a 32 x 32 grid


def _message(kind: str, payload: np.ndarray, ratio: int, **extras: np.ndarray) -> Message:
    return Message(kind=kind, run_id=RUN, sender_id="cav1", frame=7, capture_time=0.7,  # type: ignore[arg-type]
                   sender_pose=(1.0, 2.0, 0.0, 0.3), payload=payload, channel_compression=ratio, extras=extras)


def _reference_top(confidence: np.ndarray, n: int) -> list[int]:
    """The n most confident cells, ties to the lower index, by a plain sort of (-confidence, index)."""
    flat = confidence.ravel().tolist()
    return sorted(sorted(range(len(flat)), key=lambda i: (-flat[i], i))[:n])


# ---- index_dtype / select_cells --------------------------------------------------------------


def test_index_dtype_is_the_narrowest_that_fits() -> None:
    assert index_dtype(1) == np.uint16 and index_dtype(F * F) == np.uint16
    assert index_dtype(256 * 256) == np.uint16  # indices 0..65535
    assert index_dtype(256 * 256 + 1) == np.uint32
    assert index_dtype(1 << 32) == np.uint32
    for bad in (-1, (1 << 32) + 1):
        with pytest.raises(ValueError, match=rf"a grid of {bad} cells cannot be indexed on the wire"):
            index_dtype(bad)


@pytest.mark.parametrize("fraction", [0.01, 0.1, 0.25, 1 / 3, 0.5, 0.9])
def test_select_cells_takes_the_most_confident(fraction: float) -> None:
    conf = np.random.default_rng(1).random((F, F), dtype=np.float32)
    cells = select_cells(conf, fraction)
    n = round(fraction * F * F)
    assert cells.shape == (n,) and cells.dtype == np.uint16
    assert (np.diff(cells.astype(np.int64)) > 0).all()  # ascending, unique
    chosen = np.zeros(F * F, bool)
    chosen[cells] = True
    assert conf.ravel()[chosen].min() > conf.ravel()[~chosen].max()
    assert cells.tolist() == _reference_top(conf, n)


def test_select_cells_breaks_ties_by_the_lower_index() -> None:
    assert select_cells(np.ones((4, 4)), 0.25).tolist() == [0, 1, 2, 3]
    conf = np.array([[0.5, 1.0], [0.5, 0.5]])
    assert select_cells(conf, 0.5).tolist() == [0, 1]  # cell 1, then the first of the tied 0.5s
    rng = np.random.default_rng(2)
    for _ in range(20):  # many ties: a few levels only
        conf = rng.integers(0, 3, (F, F)).astype(np.float16)
        fraction = float(rng.random())
        got = select_cells(conf, fraction)
        assert got.tolist() == _reference_top(conf, round(fraction * F * F))
        assert np.array_equal(select_cells(conf, fraction), got)  # deterministic


def test_select_cells_ends_and_bad_input() -> None:
    conf = np.random.default_rng(3).random((F, F))
    none = select_cells(conf, 0.0)
    assert none.shape == (0,) and none.dtype == np.uint16
    assert select_cells(conf, 1.0).tolist() == list(range(F * F))
    assert select_cells(np.zeros((257, 257)), 0.001).dtype == np.uint32
    for fraction in (-0.01, 1.01, float("nan")):
        with pytest.raises(ValueError, match=r"fraction must be in \[0, 1\], got "):
            select_cells(conf, fraction)
    with pytest.raises(ValueError, match=r"confidence must be \[F, F\], got shape \(1, "):
        select_cells(conf.reshape(1, F, F), 0.5)
    with_nan = np.arange(16, dtype=np.float64).reshape(4, 4)
    with_nan[3, 3] = np.nan
    assert 15 not in select_cells(with_nan, 15 / 16).tolist()  # NaN: the least confident


# ---- gather / scatter ------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_gather_scatter_round_trip(dtype: type) -> None:
    rng = np.random.default_rng(4)
    x = rng.standard_normal((C, F, F)).astype(dtype)
    cells = select_cells(rng.random((F, F)), 0.2)
    values = gather(x, cells)
    assert values.shape == (cells.size, C) and values.dtype == dtype and values.flags.c_contiguous
    rows, cols = np.divmod(cells.astype(np.int64), F)  # row-major
    np.testing.assert_array_equal(values, x[:, rows, cols].T)
    dense = scatter(values, cells, x.shape)
    assert dense.shape == x.shape and dense.dtype == np.float32
    sent = np.zeros((F, F), bool)
    sent[rows, cols] = True
    np.testing.assert_array_equal(dense[:, sent], x[:, sent].astype(np.float32))
    assert not dense[:, ~sent].any()
    every = select_cells(rng.random((F, F)), 1.0)
    np.testing.assert_array_equal(scatter(gather(x, every), every, x.shape), x.astype(np.float32))
    none = select_cells(rng.random((F, F)), 0.0)
    assert gather(x, none).shape == (0, C) and not scatter(gather(x, none), none, x.shape).any()


def test_gather_scatter_refuse_misshapen_input() -> None:
    cells = np.array([0, 3], np.uint16)
    with pytest.raises(ValueError, match=r"features must be \[C, F, F\], got shape "):
        gather(np.zeros((F, F)), cells)
    for values in (np.zeros((3, C)), np.zeros((2, C + 1)), np.zeros(2)):
        with pytest.raises(ValueError, match=r"values .* and cells \(2,\) do not fit a map of "):
            scatter(values, cells, (C, F, F))


# ---- through the codec and the ego's decoder ---------------------------------------------------


@pytest.mark.parametrize("ratio", [1, 8])
def test_sparse_message_through_the_ego_decoder(ratio: int) -> None:
    sc = load_scenario(REPO / "scenarios" / "intersection.yaml", [f"comm.channel_compression={ratio}"])
    spec = ego_wire_spec(sc, C, F)
    rng = np.random.default_rng(5)
    x = rng.standard_normal((C // ratio, F, F)).astype(np.float32)  # already channel-compressed
    cells = select_cells(np.abs(x).sum(axis=0), 0.1)
    msg = _message("sparse", gather(x, cells), ratio, cells=cells)
    for key in (None, KEY):
        for comp in ("none", "zlib"):
            data = encode(Message(**{**msg.__dict__, "compression": comp}), key)
            assert len(data) <= spec["sparse"].max_message_bytes("sparse")
            got = EgoDecoder(spec, RUN, {"cav1"}, key).decode("sparse", data, "cav1")
            assert got.kind == "sparse" and got.shape == (cells.size, C // ratio) and got.dtype == "float16"
            assert got.channel_compression == ratio
            np.testing.assert_array_equal(got.extras[CELLS], cells)
            dense = scatter(got.payload, got.extras[CELLS], x.shape)
            rows, cols = np.divmod(cells.astype(np.int64), F)
            np.testing.assert_array_equal(dense[:, rows, cols], x[:, rows, cols].astype(np.float16))
            assert np.count_nonzero(np.abs(dense).sum(axis=0)) == cells.size
    # the receiver refuses what it could not scatter with
    bad = cells.copy()
    bad[-1] = F * F
    with pytest.raises(RejectedMessage) as ei:
        EgoDecoder(spec, RUN, {"cav1"}).decode("sparse", encode(_message("sparse", msg.payload, ratio, cells=bad)))
    assert ei.value.reason == "bad_indices"


# ---- which message is smaller ----------------------------------------------------------------


@pytest.mark.parametrize(("channels", "f"), [(64, 32), (8, 32), (3, 5), (1, 4), (2, 257)])
def test_sparse_is_smaller_matches_the_encoded_sizes(channels: int, f: int) -> None:
    """The helper's byte counts are the codec's, so the switch-over lands on the right cell count."""
    total = f * f
    x = np.zeros((channels, f, f), np.float32)
    dense = len(encode(_message("features", x, 1)))
    # the break-even cell count, where sparse stops being smaller
    per_cell = 2 * channels + index_dtype(total).itemsize
    even = (dense_wire_bytes(total, channels) - sparse_wire_bytes(0, total, channels)) // per_cell
    ties = 0
    for n in sorted({0, 1, total // 2, total} | {max(0, min(total, even + d)) for d in range(-2, 3)}):
        cells = np.arange(n, dtype=index_dtype(total))
        sparse = len(encode(_message("sparse", gather(x, cells), 1, cells=cells)))
        assert sparse - dense == sparse_wire_bytes(n, total, channels) - dense_wire_bytes(total, channels), n
        assert sparse_is_smaller(n, total, channels) == (sparse < dense), n
        if sparse == dense:
            ties += 1
    assert ties == (channels == 1)  # (1, 4): 6 cells cost as much as the map, and the map is sent
    assert sparse_is_smaller(0, total, channels)
    assert not sparse_is_smaller(total, total, channels)  # every cell: the indices only add bytes


def test_sparse_is_smaller_for_the_shipped_grid() -> None:
    """64 channels on 32 x 32 at 2 + 2 bytes a value and index: sparse wins up to ~98% of the cells."""
    assert sparse_is_smaller(int(0.98 * F * F), F * F, C)
    assert not sparse_is_smaller(int(0.99 * F * F), F * F, C)
    assert sparse_is_smaller(1, F * F, 1)
    assert not sparse_is_smaller(F * F // 2 + 1, F * F, 1)  # one channel: 2 + 2 bytes against 2 a cell

"""Sparse BEV features (Where2comm-style): a CAV sends only its most confident cells.

A "sparse" message (v2vsim.comm.codec) carries the values of N cells of the (C, F, F) feature
map as a (N, C) float16 payload, and their row-major indices into the F x F grid as the extra
"cells" (N,) uint16/uint32, strictly increasing. The sender picks the cells (`select_cells`),
packs them (`gather`), and sends the dense "features" message instead whenever the sparse one
would not be smaller (`sparse_is_smaller`); the receiver expands them back (`scatter`), with
zeros in the cells that were not sent. Pure numpy: the codec's side of the format, no models.
"""

from __future__ import annotations

import numpy as np

from v2vsim.comm.codec import CELLS, KIND_DTYPES

_UINT16_CELLS = 1 << 16  # indices 0..65535 fit in uint16
_MAX_CELLS = 1 << 32


def index_dtype(cells: int) -> np.dtype:
    """The narrowest wire dtype that indexes a grid of `cells` cells: uint16 up to 65536, else uint32."""
    if not 0 <= cells <= _MAX_CELLS:
        raise ValueError(f"a grid of {cells} cells cannot be indexed on the wire (at most {_MAX_CELLS})")
    return np.dtype(np.uint16 if cells <= _UINT16_CELLS else np.uint32)


def select_cells(confidence: np.ndarray, fraction: float) -> np.ndarray:
    """The row-major indices of the round(fraction * F * F) most confident cells of `confidence`
    [F, F], ascending, as index_dtype(F * F): the "cells" extra as the codec wants it.

    Ties go to the lower index (a stable sort), so the same map always yields the same message.
    NaN confidences count as the least confident.
    """
    conf = np.asarray(confidence)
    if conf.ndim != 2:
        raise ValueError(f"confidence must be [F, F], got shape {conf.shape}")
    if not 0.0 <= fraction <= 1.0:  # also refuses NaN
        raise ValueError(f"fraction must be in [0, 1], got {fraction}")
    total = conf.size
    n = round(fraction * total)
    order = np.argsort(-conf.astype(np.float64).ravel(), kind="stable")[:n]
    return np.sort(order).astype(index_dtype(total))


def gather(features: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The values [N, C] of `cells` (row-major indices) in `features` [C, F, F], same dtype:
    the "sparse" message's payload."""
    if features.ndim != 3:
        raise ValueError(f"features must be [C, F, F], got shape {features.shape}")
    c = features.shape[0]
    return np.ascontiguousarray(features.reshape(c, -1)[:, np.asarray(cells, dtype=np.intp)].T)


def scatter(values: np.ndarray, cells: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """The dense float32 map `shape` = (C, F, F) with `values` [N, C] in `cells` and zeros in the
    cells not sent: what the receiver's fusion consumes in place of a "features" payload."""
    c, h, w = shape
    idx = np.asarray(cells, dtype=np.intp)
    if values.shape != (idx.size, c) or idx.ndim != 1:
        raise ValueError(f"values {values.shape} and cells {idx.shape} do not fit a map of {shape}")
    out = np.zeros((c, h * w), np.float32)
    out[:, idx] = values.T
    return out.reshape(shape)


def _array_header_bytes(name: str, ndim: int) -> int:
    """One array's header in the codec's layout: name length, name, dtype, ndim, ndim x uint32."""
    return 1 + len(name.encode()) + 2 + 4 * ndim


def sparse_wire_bytes(n_cells: int, total_cells: int, channels: int) -> int:
    """The arrays of an uncompressed "sparse" message of `n_cells` cells of `channels` channels
    (headers and data; the rest of a message is the same for both kinds)."""
    value = np.dtype(KIND_DTYPES["sparse"]).itemsize
    index = index_dtype(total_cells).itemsize
    return _array_header_bytes("", 2) + _array_header_bytes(CELLS, 1) + n_cells * (value * channels + index)


def dense_wire_bytes(total_cells: int, channels: int) -> int:
    """The array of an uncompressed "features" message (C, F, F) with F * F = `total_cells`."""
    return _array_header_bytes("", 3) + np.dtype(KIND_DTYPES["features"]).itemsize * channels * total_cells


def sparse_is_smaller(n_cells: int, total_cells: int, channels: int) -> bool:
    """Whether sending `n_cells` of `total_cells` as "sparse" beats the dense "features" message
    on the wire (uncompressed); the sender falls back to "features" when it does not."""
    return sparse_wire_bytes(n_cells, total_cells, channels) < dense_wire_bytes(total_cells, channels)

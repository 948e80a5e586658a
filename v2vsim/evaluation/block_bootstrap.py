"""A paired difference of two dataset-level IoUs over one run's frames, with a moving-block bootstrap interval.

The statistic is a ratio of sums, IoU = sum(intersection) / sum(union) over frames, and the difference
is method IoU minus baseline IoU on the same frames (paired: both were scored on each frame). Frames of
one run are not independent (10 Hz, the scene changes slowly), so an ordinary bootstrap that draws
frames one by one would give intervals that are too narrow. The moving-block bootstrap (Kuensch 1989)
draws blocks of L consecutive frames instead, which keeps the dependence within a block; this module
uses its circular form (Politis & Romano 1992): a block may wrap from the last frame to the first, so
every frame is drawn equally often and the replicates are centred on the run's own difference, where
plain moving blocks under-draw the first and last L - 1 frames.

Block length L (`block_length`), chosen from the data:

    L = min(max(ceil(n ** (1/3)), h), max(1, n // 4))

- n ** (1/3) is the asymptotically optimal order of the block length for the block bootstrap's
  variance estimate (Hall, Horowitz & Jing 1995);
- h is the first lag at which the sample autocorrelation of the per-frame series falls below the
  white-noise band 1.96 / sqrt(n): blocks are never shorter than the correlation the run shows;
- the cap n // 4 leaves at least four blocks to resample.

The per-frame series is the linearised contribution of each frame to the difference (the delta
method's influence values, `influence`): (I_t - R U_t) / mean(U) for each method, method minus
baseline. It is defined on every frame, also those with an empty union (value 0: such a frame does
not move the ratio), where the per-frame IoU is not.

Intervals are percentile intervals of B replicates from a fixed-seed numpy Generator, so a run's
report is the same every time it is written from the same counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LEVEL = 0.95
REPLICATES = 2000
RNG_SEED = 0
WHITE_NOISE_Z = 1.96  # the two-sided 95% band of a white-noise autocorrelation: +-1.96 / sqrt(n)


@dataclass(frozen=True)
class PairedDifference:
    """Method IoU minus baseline IoU over the same frames, with its bootstrap interval."""

    diff: float
    low: float
    high: float
    block: int  # L, frames per block
    frames: int  # n, frames resampled
    replicates: int  # B, replicates drawn (those with an empty union in either method are left out)

    @property
    def excludes_zero(self) -> bool:
        return self.low > 0 or self.high < 0


def first_uncorrelated_lag(series: np.ndarray, max_lag: int) -> int:
    """The first lag h in 1..max_lag whose sample autocorrelation is below 1.96 / sqrt(n); max_lag when
    none is, and 1 for a constant series (nothing to be correlated)."""
    x = np.asarray(series, dtype=np.float64)
    n = x.size
    x = x - x.mean()
    denom = float(np.dot(x, x))
    if n < 2 or denom <= 0.0:
        return 1
    band = WHITE_NOISE_Z / math.sqrt(n)
    for h in range(1, max_lag + 1):
        if float(np.dot(x[:-h], x[h:])) / denom < band:
            return h
    return max(max_lag, 1)


def block_length(series: np.ndarray) -> int:
    """L = min(max(ceil(n^(1/3)), first lag with autocorrelation below 1.96/sqrt(n)), max(1, n // 4))."""
    n = int(np.asarray(series).size)
    cap = max(1, n // 4)
    # the cube root's float error (64 ** (1/3) = 3.9999...) must not push L one block up or down
    cube = math.ceil(round(n ** (1 / 3), 9))
    return min(max(cube, first_uncorrelated_lag(series, cap)), cap)


def influence(a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """Per frame, its linearised contribution to IoU_a - IoU_b; a, b: [n, 2] (intersection, union) on the
    same frames. None when either method's unions sum to zero (its IoU does not exist)."""
    a, b = _counts(a), _counts(b)
    ua, ub = a[:, 1].sum(), b[:, 1].sum()
    if ua <= 0 or ub <= 0:
        return None
    n = len(a)
    ra, rb = a[:, 0].sum() / ua, b[:, 0].sum() / ub
    return (a[:, 0] - ra * a[:, 1]) / (ua / n) - (b[:, 0] - rb * b[:, 1]) / (ub / n)


def circular_block_sums(values: np.ndarray, block: int, replicates: int, rng: np.random.Generator) -> np.ndarray:
    """Column sums of `replicates` circular block resamples of the rows of values [n, k]: ceil(n / block)
    blocks of consecutive rows with uniform random starts, wrapping at the end, cut to n rows. [B, k]."""
    n = len(values)
    blocks = math.ceil(n / block)
    last = n - (blocks - 1) * block  # rows taken from the last block, 1..block
    # prefix sums over the series with its first `block` rows appended: a block's sum is one subtraction
    wrapped = np.concatenate([values, values[:block]])
    prefix = np.concatenate([np.zeros((1, values.shape[1])), np.cumsum(wrapped, axis=0)])
    starts = rng.integers(0, n, size=(replicates, blocks))
    full = prefix[starts[:, :-1] + block] - prefix[starts[:, :-1]]  # [B, blocks - 1, k]
    tail = prefix[starts[:, -1] + last] - prefix[starts[:, -1]]  # [B, k]
    return full.sum(axis=1) + tail


def paired_difference(a: np.ndarray, b: np.ndarray, block: int | None = None, replicates: int = REPLICATES,
                      seed: int = RNG_SEED, level: float = LEVEL) -> PairedDifference | None:
    """IoU_a - IoU_b (sum of intersections / sum of unions of each) over the same frames, with a `level`
    circular moving-block bootstrap percentile interval; a, b: [n, 2] (intersection, union) per frame in
    frame order, row t of both the same frame. `block`: L, or None to choose it (`block_length` of the
    influence series). None when there is no interval: fewer than 2 frames, or either IoU undefined."""
    a, b = _counts(a), _counts(b)
    if a.shape != b.shape:
        raise ValueError(f"paired counts need the same frames: {a.shape} vs {b.shape}")
    z = influence(a, b) if len(a) >= 2 else None
    if z is None:
        return None
    n = len(a)
    diff = a[:, 0].sum() / a[:, 1].sum() - b[:, 0].sum() / b[:, 1].sum()
    size = block_length(z) if block is None else min(max(1, block), n)
    sums = circular_block_sums(np.concatenate([a, b], axis=1), size, replicates, np.random.default_rng(seed))
    # a replicate whose frames all have an empty union in one method has no IoU for it: left out
    ok = (sums[:, 1] > 0) & (sums[:, 3] > 0)
    if not ok.any():
        return None
    reps = sums[ok, 0] / sums[ok, 1] - sums[ok, 2] / sums[ok, 3]
    alpha = (1.0 - level) / 2
    low, high = np.quantile(reps, [alpha, 1.0 - alpha])
    return PairedDifference(float(diff), float(low), float(high), size, n, int(ok.sum()))


def _counts(c: np.ndarray) -> np.ndarray:
    arr = np.asarray(c, dtype=np.float64).reshape(-1, 2)
    if (arr < 0).any():
        raise ValueError("intersection and union counts must be non-negative")
    return arr

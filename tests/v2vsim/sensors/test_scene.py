"""The map rasters every agent builds at start (v2vsim/sensors/scene.py)."""

from __future__ import annotations

import numpy as np
import pytest

from v2vsim.sensors.scene import _mips


def _mips_by_mean(mask: np.ndarray, levels: int) -> tuple[np.ndarray, ...]:
    """The pyramid's definition: float32 mean of each 2x2 block (odd sides padded with 0), as uint8 0..255."""
    out = []
    cur = mask.astype(np.float32)
    for _ in range(levels):
        h, w = cur.shape
        cur = np.pad(cur, ((0, h % 2), (0, w % 2)))
        cur = cur.reshape(cur.shape[0] // 2, 2, cur.shape[1] // 2, 2).mean(axis=(1, 3))
        out.append(np.round(cur * 255).astype(np.uint8))
    return tuple(out)


@pytest.mark.parametrize("shape", [(256, 256), (301, 77), (5, 3), (1, 1)])
def test_marking_pyramid_is_the_block_mean_exactly(shape: tuple[int, int]) -> None:
    mask = (np.random.default_rng(sum(shape)).random(shape) < 0.3).astype(np.uint8)
    got, want = _mips(mask, 5), _mips_by_mean(mask, 5)
    assert [g.shape for g in got] == [w.shape for w in want]
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)

"""A synthetic body-frame LiDAR cloud for the perception tests (no scene, no ray casting)."""

from __future__ import annotations

import numpy as np


def cloud(seed: int = 0, n: int = 6000) -> np.ndarray:
    """[n, 4] float32 points: x, y uniform in +-40 m, z in 0-3 m, intensity in 0-1."""
    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.uniform(-40, 40, (n, 2)), rng.uniform(0, 3, (n, 1)), rng.uniform(0, 1, (n, 1))], 1)
    return pts.astype(np.float32)

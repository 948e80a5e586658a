"""The share of connected vehicles (`cavs.penetration`, issue 54): of the cavs.count vehicles the scenario places
around its junction (the area of interest), the egos are always connected and the given share of the others, drawn
per seed; the rest are placed the same way but are ordinary vehicles: SUMO drives them, they sense nothing, encode
nothing and send nothing (no agent process), and they are targets like any other car.

The draw is one permutation of the non-ego places per seed, and a share takes its first round(share x n): so for a
seed a higher penetration connects a superset of a lower one's vehicles, and a curve against penetration adds
vehicles rather than reshuffling them. null (the default): every placed vehicle is connected, as before.
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from v2vsim.config import Scenario
from v2vsim.traffic.base import cav_id


def placed_vehicles(sc: Scenario) -> list[str]:
    """Every vehicle the scenario places as a CAV candidate (cav0 first), connected or not."""
    return [cav_id(i) for i in range(sc.cavs.count)]


def connected_share_count(share: float, others: int) -> int:
    """How many of `others` non-ego places a share connects: round half up (0.5 of 3 is 2)."""
    return min(others, math.floor(share * others + 0.5))


def connected_cavs(sc: Scenario) -> list[str]:
    """The connected vehicles of a run, in cav order (module doc)."""
    placed = placed_vehicles(sc)
    share = sc.cavs.penetration
    if share is None:
        return placed
    egos = sc.cavs.egos_among(placed)
    others = [c for c in placed if c not in egos]
    order = np.random.default_rng([sc.seed, zlib.crc32(b"cavs.penetration")]).permutation(len(others))
    picked = {others[i] for i in order[:connected_share_count(share, len(others))]}
    return [c for c in placed if c in egos or c in picked]

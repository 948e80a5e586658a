"""What one CAV senses in one tick: its LiDAR sweep and/or four camera images.

Shared by `v2vsim frame` and the CAV agent process so both see the same thing. The noise
generator is seeded from (scenario seed, frame, CAV id), so a run is reproducible whichever
process or host senses it.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from v2vsim.config import Scenario
from v2vsim.sensors.camera import CameraFrame, render_cameras
from v2vsim.sensors.lidar import LidarSweep, lidar_sweep
from v2vsim.sensors.scene import Scene
from v2vsim.world.state import WorldState


@dataclass(frozen=True)
class SensorFrame:
    cav_id: str
    frame: int
    lidar: LidarSweep | None
    cameras: CameraFrame | None


def sensor_rng(seed: int, frame: int, cav_id: str) -> np.random.Generator:
    return np.random.default_rng([seed, frame, zlib.crc32(cav_id.encode())])


def sense(world: WorldState, cav_id: str, scenario: Scenario, scene: Scene,
          lidar: bool = True, cameras: bool = True) -> SensorFrame:
    """Sense from `cav_id`'s pose in `world`; `scene` is the tick's shared prism scene."""
    rng = sensor_rng(scenario.seed, world.frame, cav_id)
    sweep = lidar_sweep(world, cav_id, scenario.sensors.lidar, rng, scene=scene) if lidar else None
    cams = render_cameras(world, cav_id, scenario.sensors.cameras, scene=scene) if cameras else None
    return SensorFrame(cav_id=cav_id, frame=world.frame, lidar=sweep, cameras=cams)


def ego_ids(scenario: Scenario, present: list[str]) -> list[str]:
    """The CAVs that fuse, from `cavs.ego` (first | all | list of ids) and the CAVs present."""
    return scenario.cavs.egos_among(present)

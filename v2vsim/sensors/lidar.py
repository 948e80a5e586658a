"""A spinning LiDAR: `channels` x `points_per_channel` rays through the shared scene.

Frame of the points: origin `height_m` above the CAV's footprint centre, x forward, y left,
z up (so ground returns have z = -height_m). The world is taken as flat (pose.z ignored).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from v2vsim.config import LidarConfig
from v2vsim.sensors.raycast import RayHits, cast_columns
from v2vsim.sensors.scene import (
    GROUND_MARKING,
    GROUND_ROAD,
    HIT_BUILDING,
    HIT_GROUND,
    HIT_NONE,
    HIT_VEHICLE,
    Scene,
    actor_index,
    build_scene,
)
from v2vsim.world.state import WorldState

# Diffuse reflectivity by material (intensity = reflectivity x |cos incidence|).
REFLECTIVITY_VEHICLE = 0.75
REFLECTIVITY_BUILDING = 0.35
REFLECTIVITY_ROAD = 0.12
REFLECTIVITY_OFFROAD = 0.25
REFLECTIVITY_MARKING = 0.9  # retro-reflective paint


@dataclass(frozen=True)
class LidarSweep:
    """One sweep of one CAV. points: (P, 4) float32 x, y, z, intensity in the LiDAR frame;
    hit_actor: (P,) int32 index into world.actors, -1 for ground and buildings."""

    cav_id: str
    points: np.ndarray
    hit_actor: np.ndarray

    def hits_per_actor(self, n_actors: int) -> np.ndarray:
        """(n_actors,) number of points on each actor (visibility, dataset statistics)."""
        ids = self.hit_actor[self.hit_actor >= 0]
        return np.bincount(ids, minlength=n_actors)[:n_actors]


def lidar_beams(cfg: LidarConfig) -> tuple[np.ndarray, np.ndarray]:
    """(azimuths (N,) body frame, radians, ascending from -pi; elevations (C,) ascending)."""
    az = -math.pi + 2 * math.pi * np.arange(cfg.points_per_channel) / cfg.points_per_channel
    lo, hi = cfg.vertical_fov_deg
    el = np.radians(np.linspace(lo, hi, cfg.channels)) if cfg.channels > 1 else np.radians([0.5 * (lo + hi)])
    return az, el


def lidar_sweep(world: WorldState, cav_id: str, cfg: LidarConfig, rng: np.random.Generator,
                scene: Scene | None = None) -> LidarSweep:
    """Synthesise `cav_id`'s sweep. Pass `scene` (build_scene once per tick) to share the work."""
    if scene is None:
        scene = build_scene(world)
    me = actor_index(world, cav_id)
    pose = world.actors[me].pose
    return sweep_from(scene, cav_id, (pose.x, pose.y, pose.yaw), cfg, rng, exclude_actor=me)


def sweep_from(scene: Scene, sensor_id: str, pose: tuple[float, float, float], cfg: LidarConfig,
               rng: np.random.Generator, exclude_actor: int | None = None) -> LidarSweep:
    """A sweep from any mount: `pose` (world x, y, heading) on the ground, the LiDAR `cfg.height_m` above it (a
    CAV's roof, or a pole: a roadside unit's sensor sees over what a car's cannot, and not through a building);
    `exclude_actor`: the scene's prism of the sensor's own body, if it has one."""
    x, y, yaw = pose
    az, el = lidar_beams(cfg)
    hits = cast_columns(scene.prisms, (x, y), cfg.height_m, az + yaw, np.tan(el), max_range=cfg.range_m,
                        exclude_actor=exclude_actor)
    return _to_sweep(sensor_id, hits, az, el, x, y, yaw, scene, cfg, rng)


def _to_sweep(cav_id: str, hits: RayHits, az: np.ndarray, el: np.ndarray, x: float, y: float, yaw: float,
              scene: Scene, cfg: LidarConfig, rng: np.random.Generator) -> LidarSweep:
    valid = hits.kind != HIT_NONE
    if cfg.dropout > 0:
        valid &= rng.random(valid.shape) >= cfg.dropout
    a_idx, e_idx = np.nonzero(valid)
    kind = hits.kind[valid]
    r = hits.range[valid]
    if cfg.noise_std_m > 0:
        r = r + rng.normal(0.0, cfg.noise_std_m, r.shape)
    ca, sa = np.cos(az)[a_idx], np.sin(az)[a_idx]
    ce, se = np.cos(el)[e_idx], np.sin(el)[e_idx]
    pts = np.empty((len(r), 4), dtype=np.float32)
    pts[:, 0] = r * ce * ca
    pts[:, 1] = r * ce * sa
    pts[:, 2] = r * se

    # Intensity: material reflectivity x |cos(angle between ray and surface normal)|.
    n = hits.normal[valid]
    wa = az[a_idx] + yaw
    cos_inc = np.abs(n[:, 0] * np.cos(wa) * ce + n[:, 1] * np.sin(wa) * ce + n[:, 2] * se)
    refl = np.zeros(len(r))
    refl[kind == HIT_VEHICLE] = REFLECTIVITY_VEHICLE
    refl[kind == HIT_BUILDING] = REFLECTIVITY_BUILDING
    g = kind == HIT_GROUND
    if g.any():
        t = hits.t[valid][g]
        gxy = np.stack([x + t * np.cos(wa[g]), y + t * np.sin(wa[g])], axis=-1)
        bits = scene.assets.ground.sample(gxy)
        refl[g] = np.where(bits & GROUND_MARKING, REFLECTIVITY_MARKING,
                           np.where(bits & GROUND_ROAD, REFLECTIVITY_ROAD, REFLECTIVITY_OFFROAD))
    pts[:, 3] = np.clip(refl * cos_inc, 0.0, 1.0)
    return LidarSweep(cav_id, pts, hits.actor[valid].astype(np.int32))

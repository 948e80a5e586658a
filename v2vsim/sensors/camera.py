"""Four level pinhole cameras (front, right, left, back) rendered by column ray casting.

Each camera has pitch 0 and roll 0, so every image column is a vertical plane through the
camera centre: the 4 x width columns are cast together by `cast_columns`, one ray per pixel.

Intrinsics and extrinsics follow what camera encoders (SinBEVT, LaRa) expect:
  * intrinsics (4, 3, 3) in pixels of the rendered image, OpenCV convention (pixel centres at
    integer coordinates, principal point at the image centre ((w - 1) / 2, (h - 1) / 2));
  * extrinsics (4, 4, 4) camera-to-body: OpenCV camera frame (x right, y down, z forward) to
    the body frame (x forward, y left, z up, origin on the ground at the vehicle centre).
All cameras sit at (0, 0, height_m) in the body frame; the own body is not rendered.
"""

from __future__ import annotations

import colorsys
import math
import zlib
from dataclasses import dataclass

import numpy as np

from v2vsim.config import CamerasConfig
from v2vsim.sensors.raycast import cast_columns
from v2vsim.sensors.scene import (
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

# Palette rows (render_cameras): fixed colours, then one paint colour per actor.
P_SKY, P_ROAD, P_OFFROAD, P_BUILDING, P_GLASS, P_VEHICLES = range(6)

CAMERA_NAMES = ("front", "right", "left", "back")
CAMERA_YAWS_DEG = (0.0, -90.0, 90.0, 180.0)  # relative to the body, counter-clockwise

SUN = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])  # world-frame light direction
SKY_HORIZON = np.array([205.0, 220.0, 235.0])
SKY_ZENITH = np.array([70.0, 125.0, 205.0])
ROAD = np.array([100.0, 100.0, 104.0])
OFFROAD = np.array([92.0, 122.0, 62.0])
MARKING_GAIN = 2.3  # painted road = ROAD x gain: (230, 230, 239)
BUILDING = np.array([214.0, 194.0, 156.0])
GLASS = np.array([40.0, 48.0, 58.0])
HAZE_M = 300.0  # distance over which colours fade towards the horizon colour


@dataclass(frozen=True)
class CameraRig:
    """The four cameras: names, yaw in the body (rad), rendered size, intrinsics, camera-to-body."""

    names: tuple[str, ...]
    yaws: np.ndarray  # (4,)
    width: int
    height: int
    intrinsics: np.ndarray  # (4, 3, 3) float64
    extrinsics: np.ndarray  # (4, 4, 4) float64, camera -> body

    def to_json(self) -> dict:
        """For `cav_<id>_cameras.json`."""
        return {"names": list(self.names), "width": self.width, "height": self.height,
                "intrinsics": self.intrinsics.tolist(), "extrinsics": self.extrinsics.tolist()}


@dataclass(frozen=True)
class CameraFrame:
    """One CAV's four images (4, h, w, 3) uint8, per-pixel actor index (4, h, w) int32 (-1 none),
    and per-pixel depth along the optical axis (4, h, w) float32 (inf for sky)."""

    cav_id: str
    images: np.ndarray
    rig: CameraRig
    actor_index: np.ndarray
    depth: np.ndarray

    def pixels_per_actor(self, n_actors: int) -> np.ndarray:
        """(n_actors,) number of pixels showing each actor, over all four cameras."""
        ids = self.actor_index[self.actor_index >= 0]
        return np.bincount(ids, minlength=n_actors)[:n_actors]


def camera_rig(cfg: CamerasConfig) -> CameraRig:
    """Intrinsics and extrinsics of the rendered (render_scale) images; square pixels."""
    w = max(1, int(round(cfg.width * cfg.render_scale)))
    h = max(1, int(round(cfg.height * cfg.render_scale)))
    f = (w / 2) / math.tan(math.radians(cfg.fov_deg) / 2)
    k = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    yaws = np.radians(np.array(CAMERA_YAWS_DEG))
    ext = np.zeros((4, 4, 4))
    for i, yaw in enumerate(yaws):
        c, s = math.cos(yaw), math.sin(yaw)
        ext[i, :3, 0] = (s, -c, 0.0)  # camera x (right)
        ext[i, :3, 1] = (0.0, 0.0, -1.0)  # camera y (down)
        ext[i, :3, 2] = (c, s, 0.0)  # camera z (forward)
        ext[i, :3, 3] = (0.0, 0.0, cfg.height_m)
        ext[i, 3, 3] = 1.0
    return CameraRig(CAMERA_NAMES, yaws, w, h, np.repeat(k[None], 4, axis=0), ext)


def vehicle_colour(actor_id: str) -> np.ndarray:
    """A stable paint colour (RGB 0..255) from the actor id (crc32, not Python's salted hash)."""
    hsh = zlib.crc32(actor_id.encode())
    hue = (hsh % 360) / 360.0
    sat = 0.35 + 0.5 * ((hsh >> 9) % 100) / 100.0
    val = 0.45 + 0.5 * ((hsh >> 17) % 100) / 100.0
    return np.array(colorsys.hsv_to_rgb(hue, sat, val)) * 255.0


def render_cameras(world: WorldState, cav_id: str, cfg: CamerasConfig, scene: Scene | None = None,
                   rig: CameraRig | None = None) -> CameraFrame:
    """Render `cav_id`'s four cameras. Pass `scene` (build_scene once per tick) to share the work."""
    if scene is None:
        scene = build_scene(world)
    if rig is None:
        rig = camera_rig(cfg)
    me = actor_index(world, cav_id)
    pose = world.actors[me].pose
    w, h = rig.width, rig.height
    fx, fy = rig.intrinsics[0, 0, 0], rig.intrinsics[0, 1, 1]
    cx, cy = rig.intrinsics[0, 0, 2], rig.intrinsics[0, 1, 2]

    xn = (np.arange(w) - cx) / fx  # right per unit depth
    col_az = (rig.yaws[:, None] - np.arctan(xn)[None, :]).reshape(-1) + pose.yaw  # (4w,)
    col_scale = np.tile(1.0 / np.sqrt(1.0 + xn * xn), 4)  # horizontal distance -> depth
    q = -(np.arange(h)[::-1] - cy) / fy  # up per unit depth, ascending (bottom row first)
    hits = cast_columns(scene.prisms, (pose.x, pose.y), cfg.height_m, col_az, q, col_scale,
                        max_range=1e4, exclude_actor=me)

    # Shade per ray with scalars only (palette index, light, haze), then gather colours once:
    # rgb = palette[index] * light * (1 - fog) + horizon * fog.
    n_act = len(world.actors)
    palette = np.concatenate([
        np.stack([SKY_ZENITH, ROAD, OFFROAD, BUILDING, GLASS]),
        np.array([vehicle_colour(a.id) for a in world.actors]).reshape(n_act, 3),
    ]).astype(np.float32)
    kind, t, tan = hits.kind, hits.t, hits.tan_el
    index = np.zeros(kind.shape, dtype=np.int32)  # P_SKY
    light = np.ones(kind.shape, dtype=np.float32)
    with np.errstate(over="ignore"):
        fog = (1.0 - np.exp(-np.minimum(t, 1e6) / HAZE_M)).astype(np.float32)
    # Sky: horizon -> zenith gradient (fog = 1 at the horizon, 0 at 45 degrees up).
    sky = kind == HIT_NONE
    fog[sky] = 1.0 - np.clip(np.arctan(np.maximum(tan[sky], 0.0)) / (math.pi / 4), 0.0, 1.0)

    g = kind == HIT_GROUND
    if g.any():
        tg = t[g]
        azg = np.broadcast_to(col_az[:, None], kind.shape)[g]
        gxy = np.stack([pose.x + tg * np.cos(azg), pose.y + tg * np.sin(azg)], axis=-1)
        bits = scene.assets.ground.sample(gxy)
        # Paint brightens the road by up to MARKING_GAIN, blended by its coverage of the pixel's
        # lateral footprint (t / f metres), so distant lines fade rather than alias into dots.
        cov = scene.assets.ground.marking_coverage(gxy, tg / fx)
        road = ((bits & GROUND_ROAD) > 0) | (cov > 0)  # paint is on tarmac even past a road's edge
        # Off-road: coarse world-fixed mottling (a texture gradient, i.e. a depth cue).
        mott = np.sin(gxy[:, 0] * 0.37) * np.sin(gxy[:, 1] * 0.29)
        index[g] = np.where(road, P_ROAD, P_OFFROAD)
        light[g] = (0.55 + 0.45 * SUN[2]) * np.where(road, 1.0 + (MARKING_GAIN - 1.0) * cov,
                                                     1.0 + 0.12 * mott)

    solid = (kind == HIT_VEHICLE) | (kind == HIT_BUILDING)
    if solid.any():
        n = hits.normal[solid]
        act = hits.actor[solid]
        veh = act >= 0
        idx = np.where(veh, P_VEHICLES + act, P_BUILDING)
        # Cars (not trucks): dark glass band on the sides (a cue for orientation and scale).
        hgt = np.array([a.extent[2] for a in world.actors] + [1.0])[act]  # act -1 -> the 1.0
        z = cfg.height_m + t[solid] * tan[solid]
        glass = veh & (n[:, 2] < 0.5) & (hgt < 2.5) & (z > 0.55 * hgt) & (z < 0.92 * hgt)
        index[solid] = np.where(glass, P_GLASS, idx)
        light[solid] = 0.5 + 0.5 * np.clip(n[:, 0] * SUN[0] + n[:, 1] * SUN[1] + n[:, 2] * SUN[2], 0.0, 1.0)

    # (4w, h) columns with rows bottom-up -> (4, h, w) images with row 0 at the top.
    def to_img(a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.swapaxes(a.reshape(4, w, h)[:, :, ::-1], 1, 2))

    lit = to_img(light * (1.0 - fog))[..., None]
    fog_img = to_img(fog)[..., None]
    rgb = palette[to_img(index)] * lit + SKY_HORIZON.astype(np.float32) * fog_img
    images = np.clip(rgb + 0.5, 0, 255).astype(np.uint8)
    actor_img = to_img(np.where(kind == HIT_VEHICLE, hits.actor, -1).astype(np.int32))
    depth = to_img((t * col_scale[:, None]).astype(np.float32))
    return CameraFrame(cav_id, images, rig, actor_img, depth)

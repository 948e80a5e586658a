"""`v2vsim bench sensors`: time the LiDAR, the four cameras and BEV ground truth on one thread.

The scene is a hand-built junction (two crossing 4-lane roads, buildings on the corners,
~40 vehicles, 4 CAVs), so the benchmark needs neither SUMO nor highway-env. `--out DIR`
also writes preview PNGs (camera images, a LiDAR bird's-eye scatter, the GT masks).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from v2vsim.config import BevConfig, CamerasConfig, LidarConfig
from v2vsim.world.geometry import Pose
from v2vsim.world.state import Actor, Building, StaticMap, WorldState

LANE_W = 3.5
ARM_M = 150.0


def demo_map() -> StaticMap:
    """A cross junction at the origin: 2 lanes each way on both roads, buildings on the corners."""
    half = 2 * LANE_W
    roads = (np.array([[-ARM_M, -half], [ARM_M, -half], [ARM_M, half], [-ARM_M, half]]),
             np.array([[-half, -ARM_M], [half, -ARM_M], [half, ARM_M], [-half, ARM_M]]))
    marks: list[np.ndarray] = []
    dashed: list[bool] = []
    for sign in (-1.0, 1.0):
        for off, dash in ((0.0, False), (LANE_W, True), (-LANE_W, True), (half - 0.2, False),
                          (-half + 0.2, False)):
            xs = np.array([sign * half, sign * ARM_M])
            marks.append(np.stack([xs, np.full(2, off)], axis=-1))  # along x (east/west arms)
            marks.append(np.stack([np.full(2, off), xs], axis=-1))  # along y (north/south arms)
            dashed += [dash, dash]
    buildings = (
        Building("b_ne", np.array([[14.0, 14.0], [45.0, 14.0], [45.0, 40.0], [14.0, 40.0]]), 12.0),
        Building("b_nw", np.array([[-14.0, 14.0], [-14.0, 50.0], [-30.0, 50.0], [-30.0, 28.0],
                                   [-55.0, 28.0], [-55.0, 14.0]]), 9.0),  # L-shaped
        Building("b_sw", np.array([[-40.0, -14.0], [-14.0, -14.0], [-14.0, -35.0], [-40.0, -35.0]]), 15.0),
        Building("b_se", np.array([[14.0, -14.0], [30.0, -14.0], [30.0, -30.0], [14.0, -30.0]]), 8.0),
    )
    return StaticMap(roads, tuple(marks), tuple(dashed), buildings, (-ARM_M, -ARM_M, ARM_M, ARM_M))


def demo_world(n_vehicles: int = 40, seed: int = 0, static: StaticMap | None = None) -> WorldState:
    """The demo map with 4 CAVs approaching the junction, one per arm, and random traffic on lanes."""
    rng = np.random.default_rng(seed)
    static = static or demo_map()
    actors: list[Actor] = []
    # Lanes: (heading, offset of the lane centre to the left of the heading); right-hand traffic.
    lanes = [(yaw, -k * LANE_W) for yaw in (0.0, math.pi, math.pi / 2, -math.pi / 2) for k in (0.5, 1.5)]

    def place(lane: int, s: float) -> tuple[float, float, float]:
        """Position `s` metres along the lane's road axis (negative = before the junction)."""
        yaw, off = lanes[lane]
        c, sn = math.cos(yaw), math.sin(yaw)
        return s * c - off * sn, s * sn + off * c, yaw

    cav_slots = [(0, -22.0), (2, -18.0), (4, -25.0), (6, -20.0)]
    taken: list[tuple[int, float, float]] = []  # lane, position, length
    for i, (lane, s) in enumerate(cav_slots):
        x, y, yaw = place(lane, s)
        actors.append(Actor(f"cav{i}", "car", True, Pose(x, y, 0.0, yaw), (4.6, 1.9, 1.5), 8.0))
        taken.append((lane, s, 4.6))
    for _ in range(10000):
        if len(actors) >= n_vehicles + len(cav_slots):
            break
        lane = int(rng.integers(len(lanes)))
        s = float(rng.uniform(-ARM_M + 10, ARM_M - 10))
        truck = rng.random() < 0.15
        ext = (9.0, 2.5, 3.2) if truck else (float(rng.uniform(3.9, 5.0)), float(rng.uniform(1.7, 2.0)),
                                             float(rng.uniform(1.4, 1.8)))
        clear = abs(s) - ext[0] / 2 > 2 * LANE_W + 1.0  # not inside the junction
        if not clear or any(ln == lane and abs(s - s2) < (ext[0] + l2) / 2 + 2.0 for ln, s2, l2 in taken):
            continue
        x, y, yaw = place(lane, s)
        yaw += float(rng.normal(0, 0.02))
        actors.append(Actor(f"veh{len(actors)}", "truck" if truck else "car", False,
                            Pose(x, y, 0.0, yaw), ext, 10.0))
        taken.append((lane, s, ext[0]))
    return WorldState(0.0, 0, tuple(actors), static)


def _median_ms(fn: Callable[[], object], runs: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def save_previews(out: Path, world: WorldState, lidar_cfg: LidarConfig, cam_cfg: CamerasConfig,
                  bev: BevConfig, cav_id: str) -> list[Path]:
    """Camera PNGs, a LiDAR BEV scatter (ego up) and GT masks for one CAV; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    from v2vsim.evaluation.gt import bev_ground_truth, visible_actor_ids
    from v2vsim.sensors.camera import render_cameras
    from v2vsim.sensors.lidar import lidar_sweep
    from v2vsim.sensors.scene import build_map_assets, build_scene

    out.mkdir(parents=True, exist_ok=True)
    assets = build_map_assets(world.static)
    scene = build_scene(world, assets)
    rng = np.random.default_rng(0)
    sweeps = [lidar_sweep(world, a.id, lidar_cfg, rng, scene=scene) for a in world.cavs]
    frames = [render_cameras(world, a.id, cam_cfg, scene=scene) for a in world.cavs]
    me = next(i for i, a in enumerate(world.cavs) if a.id == cav_id)
    paths = []
    fr = frames[me]
    for k, name in enumerate(fr.rig.names):
        p = out / f"{cav_id}_cam{k}_{name}.png"
        Image.fromarray(fr.images[k]).resize((fr.rig.width * 3, fr.rig.height * 3), Image.NEAREST).save(p)
        paths.append(p)
    strip = np.concatenate([fr.images[2], fr.images[0], fr.images[1], fr.images[3]], axis=1)
    p = out / f"{cav_id}_cams_left_front_right_back.png"
    Image.fromarray(strip).resize((strip.shape[1] * 2, strip.shape[0] * 2), Image.NEAREST).save(p)
    paths.append(p)

    pts = sweeps[me].points
    fig, ax = plt.subplots(figsize=(8, 8))
    # Ego up the page: plot (-y, x), i.e. left of the vehicle on the left.
    onv = sweeps[me].hit_actor >= 0
    ax.scatter(-pts[~onv, 1], pts[~onv, 0], s=0.3, c=pts[~onv, 2], cmap="viridis")
    ax.scatter(-pts[onv, 1], pts[onv, 0], s=0.6, c="red")
    ax.set_xlim(-50, 50)
    ax.set_ylim(-50, 50)
    ax.set_aspect("equal")
    ax.set_title(f"{cav_id} LiDAR (ego up; red = vehicle hits)")
    p = out / f"{cav_id}_lidar_bev.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)

    vis = visible_actor_ids(sweeps, frames, world)
    gt = bev_ground_truth(world, cav_id, bev, vis, assets=assets)
    rgb = np.zeros((bev.cells, bev.cells, 3), dtype=np.uint8)
    rgb[gt["road"]] = (90, 90, 90)
    rgb[gt["lane"]] = (255, 255, 255)
    rgb[gt["dynamic"]] = (0, 0, 255)
    rgb[gt["visible"]] = (255, 60, 60)
    p = out / f"{cav_id}_gt_overlay.png"
    Image.fromarray(rgb).resize((bev.cells * 3, bev.cells * 3), Image.NEAREST).save(p)
    paths.append(p)
    for key, mask in gt.items():
        p = out / f"{cav_id}_gt_{key}.png"
        Image.fromarray(mask.astype(np.uint8) * 255).save(p)
        paths.append(p)
    return paths


def main(argv: list[str] | None = None) -> int:
    """Print median ms per LiDAR sweep, four-camera render and GT frame (one thread); 0 on success."""
    ap = argparse.ArgumentParser(prog="v2vsim bench sensors", description=__doc__)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--vehicles", type=int, default=40)
    ap.add_argument("--out", type=Path, default=None, help="also write preview PNGs here")
    args = ap.parse_args(argv)
    # The sensors are plain numpy (single-threaded); torch is not imported here.
    from v2vsim.evaluation.gt import bev_ground_truth, gt_boxes
    from v2vsim.sensors.camera import camera_rig, render_cameras
    from v2vsim.sensors.lidar import lidar_sweep
    from v2vsim.sensors.scene import build_map_assets, build_scene

    lidar_cfg, cam_cfg, bev = LidarConfig(), CamerasConfig(), BevConfig()
    static = demo_map()
    world = demo_world(args.vehicles, static=static)
    cav = world.cavs[0].id
    t0 = time.perf_counter()
    assets = build_map_assets(static)
    assets_ms = (time.perf_counter() - t0) * 1e3
    scene = build_scene(world, assets)
    rig = camera_rig(cam_cfg)
    rng = np.random.default_rng(0)
    vis = frozenset(a.id for a in world.actors)
    sweep = lidar_sweep(world, cav, lidar_cfg, rng, scene=scene)

    rows = [
        ("map assets (once per map)", assets_ms),
        ("scene build (once per tick)", _median_ms(lambda: build_scene(world, assets), args.runs)),
        (f"lidar sweep {lidar_cfg.channels}x{lidar_cfg.points_per_channel}",
         _median_ms(lambda: lidar_sweep(world, cav, lidar_cfg, rng, scene=scene), args.runs)),
        (f"4-camera render {rig.width}x{rig.height}",
         _median_ms(lambda: render_cameras(world, cav, cam_cfg, scene=scene, rig=rig), args.runs)),
        (f"gt masks {bev.cells}x{bev.cells}",
         _median_ms(lambda: bev_ground_truth(world, cav, bev, vis, assets=assets), args.runs)),
        ("gt boxes", _median_ms(lambda: gt_boxes(world, cav, bev), args.runs)),
    ]
    print(f"sensors bench: {len(world.actors)} vehicles, {len(static.buildings)} buildings, "
          f"{len(scene.prisms)} prisms, {len(sweep.points)} points/sweep, one thread, "
          f"median of {args.runs}")
    for name, ms in rows:
        print(f"  {name:<32s} {ms:8.2f} ms")
    if args.out is not None:
        for p in save_previews(args.out, world, lidar_cfg, cam_cfg, bev, cav):
            print(f"  wrote {p}")
    return 0

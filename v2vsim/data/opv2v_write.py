"""Writing the OPV2V layout (v2vsim.data.opv2v_layout): `export_opv2v(native_root, out)` turns a recorded v2vsim
dataset (docs/dataset.md) into

    out/<train|validate|test>/<scenario>/data_protocol.yaml
    out/<split>/<scenario>/<cav id>/<NNNNNN>.pcd | .yaml | _camera0..3.png | _bev_*.png

from its frames and its saved traffic (for the vehicles' heights and speeds, which the frames do not keep);
`record_opv2v_dataset` is `v2vsim dataset --format opv2v` (record, then export). v2vsim.data.opv2v_read reads such
a folder back. docs/dataset.md, "OPV2V format", has the conversion table and what is derived or absent.
"""

from __future__ import annotations

import json
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from PIL import Image

from v2vsim.data.carla_frames import (
    F4,
    box_to_carla,
    camera_cords,
    carla_pose_matrix,
    intrinsic_to_carla,
    planar_pose_matrix,
    points_to_carla,
    pose_to_carla,
)
from v2vsim.data.layout import DatasetError, unpack_masks
from v2vsim.data.opv2v_layout import CAMERAS, EXTRA, MASK_FILES, PROTOCOL, SPLIT_DIRS, dump_yaml, load_yaml
from v2vsim.data.pcd import write_pcd
from v2vsim.data.store import FrameStore
from v2vsim.world.state import Actor, WorldState


def _floats(a) -> list:
    return np.asarray(a, dtype=np.float64).tolist()


def vehicle_entry(actor: Actor) -> dict:
    """OPV2V `vehicles` entry of an actor (speed in km/h, as OPV2V's ego_speed)."""
    p = actor.pose
    return {**box_to_carla(p.x, p.y, p.z, p.yaw, *actor.extent), "speed": float(actor.speed) * 3.6}


def camera_entries(pose: tuple, lidar_height_m: float, intrinsics: np.ndarray, extrinsics: np.ndarray) -> dict:
    """`camera0..3` of a CAV's yaml from its v2vsim rig (camera-to-body extrinsics, OpenCV axes)."""
    body = planar_pose_matrix(*pose)
    lidar_c = F4 @ (body @ _translation(0.0, 0.0, lidar_height_m)) @ F4  # LiDAR-to-world, CARLA frames
    out = {}
    for i in range(CAMERAS):
        cam_world = body @ extrinsics[i].astype(np.float64)  # OpenCV camera -> v2vsim world
        cords = camera_cords(cam_world)
        lidar_to_cam = np.linalg.inv(carla_pose_matrix(cords)) @ lidar_c
        out[f"camera{i}"] = {"cords": cords, "extrinsic": _floats(lidar_to_cam),
                             "intrinsic": _floats(intrinsic_to_carla(intrinsics[i]))}
    return out


def _translation(x: float, y: float, z: float) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = (x, y, z)
    return out


def write_opv2v_frame(scenario_dir: Path, k: int, frame: Mapping, world: WorldState, meta: dict,
                      ids: dict[str, int]) -> None:
    """Every CAV's files of native frame `k` (a frame's arrays, v2vsim.data.layout) under scenario_dir."""
    cavs = [str(c) for c in frame["cavs"]]
    height = float(meta["lidar_height_m"])
    cells = int(meta["bev"]["cells"])
    seen = {c: {str(x) for x in frame[f"seen_{c}"]} for c in cavs}
    union = set().union(*seen.values()) if seen else set()
    stem = f"{k:06d}"
    for j, c in enumerate(cavs):
        folder = scenario_dir / str(ids[c])
        folder.mkdir(parents=True, exist_ok=True)
        pose = tuple(float(v) for v in frame["poses"][j])
        x, y, z, yaw = pose
        lidar = np.asarray(frame[f"points_{c}"], dtype=np.float64).copy()
        lidar[:, 2] -= height  # body frame (origin on the ground) -> LiDAR frame
        write_pcd(folder / f"{stem}.pcd", points_to_carla(lidar))
        actor = world.actor(c)
        doc: dict = {
            "lidar_pose": pose_to_carla(x, y, z + height, yaw),
            "true_ego_pos": pose_to_carla(x, y, z, yaw),
            "predicted_ego_pos": pose_to_carla(x, y, z, yaw),  # no GPS noise in a dataset (comm.pose_noise is live)
            "ego_speed": float(actor.speed) * 3.6 if actor is not None else 0.0,
            "vehicles": {ids[v]: vehicle_entry(world.actor(v)) for v in sorted(seen[c] - {c})
                         if world.actor(v) is not None},
        }
        unseen = [str(b) for b in frame[f"boxids_{c}"] if str(b) not in union]
        doc[EXTRA] = {"id": c, "self": vehicle_entry(actor) if actor is not None else None,
                      "unseen_vehicles": {ids[v]: vehicle_entry(world.actor(v)) for v in unseen}}
        if f"images_{c}" in frame:
            images = frame[f"images_{c}"]
            doc.update(camera_entries(pose, height, frame[f"intrinsics_{c}"], frame[f"extrinsics_{c}"]))
            for i in range(CAMERAS):
                Image.fromarray(np.asarray(images[i], dtype=np.uint8)).save(folder / f"{stem}_camera{i}.png")
        masks = unpack_masks(frame[f"gt_{c}"], cells)
        for name, suffix in MASK_FILES.items():
            Image.fromarray(masks[name].astype(np.uint8) * 255).save(folder / f"{stem}_{suffix}.png")
        dump_yaml(doc, folder / f"{stem}.yaml")


def _actor_ids(worlds: list[WorldState]) -> dict[str, int]:
    """v2vsim actor id -> OPV2V integer id: 0, 1, ... in order of first appearance (deterministic per run)."""
    ids: dict[str, int] = {}
    for w in worlds:
        for a in w.actors:
            ids.setdefault(a.id, len(ids))
    return ids


def _run_worlds(run_dir: Path) -> list[WorldState]:
    from v2vsim.data.record import TRAFFIC_DIR, load_traffic

    info = run_dir / TRAFFIC_DIR / "traffic.json"
    if not info.is_file():
        raise DatasetError(f"{info}: missing; the OPV2V export needs the run's saved traffic (vehicle heights and "
                           "speeds): record the dataset again with this v2vsim")
    meta = json.loads(info.read_text())
    worlds = load_traffic(run_dir, meta["frames_asked"], tuple(meta["overrides"]))
    if worlds is None:
        raise DatasetError(f"{run_dir / TRAFFIC_DIR}: unreadable saved traffic")
    return worlds


def export_opv2v(native_root: Path, out: Path, log=sys.stderr) -> list[Path]:
    """Write every run of the v2vsim dataset at `native_root` in OPV2V's layout under `out`; returns the
    scenario folders. A scenario folder already complete (its data_protocol.yaml, written last, names the same
    run and frame count) is kept; a partial one is written again."""
    store = FrameStore(Path(native_root))
    written = []
    for r in store.manifest["runs"]:
        meta = store.runs[r["name"]]
        scen = Path(out) / SPLIT_DIRS[r["split"]] / r["name"]
        proto = scen / PROTOCOL
        if proto.is_file():
            old = load_yaml(proto).get(EXTRA) or {}
            if old.get("run") == r["name"] and old.get("frames") == meta["frames"]:
                written.append(scen)
                continue
        if scen.exists():
            shutil.rmtree(scen)
        scen.mkdir(parents=True)
        worlds = _run_worlds(store.root / r["name"])
        ids = _actor_ids(worlds[: meta["frames"]])
        for k in range(meta["frames"]):
            with store.frame(r["name"], k) as f:
                write_opv2v_frame(scen, k, f, worlds[k], meta, ids)
            print(f"\ropv2v {r['name']}: frame {k + 1}/{meta['frames']}   ", end="", file=log, flush=True)
        dump_yaml({EXTRA: {
            "run": r["name"], "scenario": meta["scenario"], "source": meta["source"], "seed": meta["seed"],
            "split": r["split"], "frames": meta["frames"], "rate_hz": meta["rate_hz"], "bev": meta["bev"],
            "range_m": meta["range_m"], "lidar_height_m": meta["lidar_height_m"], "modality": meta["modality"],
            "cameras": meta["cameras"], "overrides": list(meta.get("overrides", [])),
            "actor_ids": {i: a for a, i in ids.items()},
            "note": "written by v2vsim from its own simulation, not by CARLA/OpenCDA (docs/dataset.md)"}}, proto)
        written.append(scen)
    if written:
        print(file=log)
    return written


NATIVE_DIR = "v2vsim"  # `v2vsim dataset --format opv2v`: the v2vsim recording the OPV2V folders are made from


def record_opv2v_dataset(scenario_path: str, seeds: list[int], frames: int, out: Path, split: str = "train",
                         overrides: tuple[str, ...] = (), cameras: bool = False, log=sys.stderr,
                         traffic_only: bool = False, jobs: int = 1) -> Path:
    """`v2vsim dataset --format opv2v`: record (resumable, as the native format) into out/v2vsim/, then write
    every run of it in OPV2V's layout under out/<train|validate|test>/. Returns `out`."""
    from v2vsim.data.record import record_dataset

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out}: is a file, not a folder")
    if out.is_dir():
        other = sorted(p.name for p in out.iterdir() if p.name not in (NATIVE_DIR, *SPLIT_DIRS.values()))
        if other:
            raise DatasetError(f"--out {out}: not empty and not an OPV2V folder of v2vsim's (it holds "
                               f"{', '.join(other[:3])}{', ...' if len(other) > 3 else ''}); use a new or empty folder")
    native = record_dataset(scenario_path, seeds, frames, out / NATIVE_DIR, split=split, overrides=overrides,
                            cameras=cameras, log=log, traffic_only=traffic_only, jobs=jobs)
    if not traffic_only:
        export_opv2v(native, out, log=log)
    return out

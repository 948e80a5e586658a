"""The OPV2V dataset layout (OpenCOOD's docs/md_files/data_intro.md, data_annotation_tutorial.md), both ways.

Writing: `export_opv2v(native_root, out)` turns a recorded v2vsim dataset (docs/dataset.md) into

    out/<train|validate|test>/<scenario>/data_protocol.yaml
    out/<split>/<scenario>/<cav id>/<NNNNNN>.pcd | .yaml | _camera0..3.png | _bev_*.png

from its frames and its saved traffic (for the vehicles' heights and speeds, which the frames do not keep).
Reading: `OPV2VStore(root)` reads such a folder (ours, or OPV2V itself) into the frames `FrameStore` gives
for a native dataset (same keys, v2vsim's frames and units), so `CooperativeDataset` and `v2vsim train`
take either. docs/dataset.md, "OPV2V format", has the conversion table and what is derived or absent.
"""

from __future__ import annotations

import json
import re
import shutil
import sys
from collections.abc import Iterator, Mapping
from functools import cached_property
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from v2vsim.data.carla_frames import (
    F4,
    box_from_carla,
    box_to_carla,
    camera_cords,
    camera_from_cords,
    carla_pose_matrix,
    intrinsic_from_carla,
    intrinsic_to_carla,
    planar_pose_matrix,
    points_to_carla,
    pose_from_carla,
    pose_to_carla,
    world_boxes_to_body,
)
from v2vsim.data.layout import GT_MASKS, DatasetError, pack_masks, unpack_masks
from v2vsim.data.pcd import PcdError, read_pcd, write_pcd
from v2vsim.world.state import Actor, WorldState

PROTOCOL = "data_protocol.yaml"
# v2vsim split -> OPV2V split folder, and back (OPV2V's test_culvercity and other test_* are eval splits too).
SPLIT_DIRS = {"train": "train", "val": "validate", "eval": "test"}
DIR_SPLITS = {"train": "train", "validate": "val", "validation": "val", "val": "val", "test": "eval"}
# v2vsim mask -> the BEV ground-truth file of OPV2V's camera track (OpenCOOD logreplay / CoBEVT names).
MASK_FILES = {"dynamic": "bev_dynamic", "road": "bev_static", "lane": "bev_lane",
              "visible_self": "bev_visibility", "visible": "bev_visibility_corp"}
REQUIRED_MASKS = ("dynamic", "road", "lane")  # the others can be derived from the `vehicles` lists
CAMERAS = 4
OPV2V_BEV_SIZE_M = 100.0  # CoBEVT / logreplay: radius 50 m, 256 x 256 px
OPV2V_RANGE_M = 70.0  # OpenCOOD's COM_RANGE
OPV2V_RATE_HZ = 10.0
EXTRA = "v2vsim"  # our own key in a CAV's yaml and in data_protocol.yaml (OpenCOOD reads neither)
STEM = re.compile(r"^(-?[0-9]+)\.yaml$")
CAV_DIR = re.compile(r"^-?[0-9]+$")


# ---------------------------------------------------------------------------------------------- YAML


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # libyaml's parser when PyYAML has it
    """Safe YAML with floats such as `1e-05` (no dot) read as floats, as OpenCOOD's loader does."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?|[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)"
               r"|\.[0-9_]+(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+0123456789."))


def load_yaml(path: Path) -> dict:
    try:
        doc = yaml.load(path.read_text(), Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
    except (OSError, yaml.YAMLError) as e:
        raise DatasetError(f"{path}: unreadable YAML ({e})") from None
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a mapping at the top")
    return doc


def _dump(doc: dict, path: Path) -> None:
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    path.write_text(yaml.dump(doc, Dumper=dumper, default_flow_style=None, sort_keys=True))


def _floats(a) -> list:
    return np.asarray(a, dtype=np.float64).tolist()


# ---------------------------------------------------------------------------------------------- writing


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
        _dump(doc, folder / f"{stem}.yaml")


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
    from v2vsim.data.torch_dataset import FrameStore

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
        _dump({EXTRA: {
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


# ---------------------------------------------------------------------------------------------- reading


def _is_cav_dir(p: Path) -> bool:
    return p.is_dir() and CAV_DIR.fullmatch(p.name) is not None


def is_scenario_dir(p: Path) -> bool:
    """A scenario folder: data_protocol.yaml, or integer-named CAV folders holding timestamp yamls."""
    if not p.is_dir():
        return False
    if (p / PROTOCOL).is_file():
        return True
    return any(_is_cav_dir(c) and any(STEM.match(f.name) for f in c.iterdir()) for c in p.iterdir())


def _split_of(name: str) -> str | None:
    if name in DIR_SPLITS:
        return DIR_SPLITS[name]
    return "eval" if name.startswith("test_") else None


def find_scenarios(root: Path) -> list[tuple[str, str, Path]]:
    """(split, split folder name, scenario folder) of an OPV2V folder: a split root (train/, validate/,
    test/...), a split folder (its name gives the split; another name counts as train), or one scenario."""
    root = Path(root)
    if not root.is_dir():
        return []
    if is_scenario_dir(root):
        return [("train", root.parent.name, root)]
    children = sorted(p for p in root.iterdir() if p.is_dir())
    scen = [p for p in children if is_scenario_dir(p)]
    if scen:
        split = _split_of(root.name) or "train"
        return [(split, root.name, p) for p in scen]
    out = []
    for d in children:
        split = _split_of(d.name)
        if split is not None:
            out += [(split, d.name, p) for p in sorted(d.iterdir()) if is_scenario_dir(p)]
    return out


def is_opv2v(root: Path) -> bool:
    """An OPV2V-layout folder (and not a native dataset, which has a manifest.json)."""
    root = Path(root)
    return not (root / "manifest.json").is_file() and bool(find_scenarios(root))


class _Run:
    """One scenario folder: its CAV folders, their timestamps, and the run's settings."""

    def __init__(self, store_root: Path, split: str, split_dir: str, folder: Path) -> None:
        self.folder = folder
        self.split, self.split_dir = split, split_dir
        self.extra: dict = {}
        proto = folder / PROTOCOL
        if proto.is_file():
            text = proto.read_text(errors="replace")
            if re.search(rf"^{EXTRA}:", text, flags=re.M):  # OPV2V's own protocols are large: parse only ours
                self.extra = load_yaml(proto).get(EXTRA) or {}
        names = {int(k): str(v) for k, v in (self.extra.get("actor_ids") or {}).items()}
        self.cav_dirs: dict[str, Path] = {}  # display id -> folder
        self.cav_int: dict[str, int] = {}
        self.stamps: dict[str, dict[int, str]] = {}  # display id -> timestamp -> file stem
        for d in sorted(p for p in folder.iterdir() if _is_cav_dir(p)):
            stems = {int(m.group(1)): m.group(1) for m in (STEM.match(f.name) for f in d.iterdir()) if m}
            if not stems:
                continue
            cid = names.get(int(d.name), d.name)
            self.cav_dirs[cid], self.cav_int[cid], self.stamps[cid] = d, int(d.name), stems
        if not self.cav_dirs:
            raise DatasetError(f"{folder}: no CAV folder (integer-named, with <timestamp>.yaml files)")
        self.names = names
        self.timestamps = sorted(set().union(*(set(s) for s in self.stamps.values())))
        additional = store_root / "additional" / split_dir / folder.name
        self.mask_dirs = {c: [d, additional / d.name] for c, d in self.cav_dirs.items()}
        first_cav = sorted(self.cav_dirs)[0]
        first = self.stamps[first_cav][min(self.stamps[first_cav])]
        self.has_masks = {m: self.mask_file(first_cav, first, m) is not None for m in MASK_FILES}
        self.cameras = (self.cav_dirs[first_cav] / f"{first}_camera0.png").is_file()
        cells = self.extra.get("bev", {}).get("cells")
        if cells is None:
            dyn = self.mask_file(first_cav, first, "dynamic")
            cells = Image.open(dyn).size[0] if dyn is not None else 256
        self.bev = {"size_m": float(self.extra.get("bev", {}).get("size_m", OPV2V_BEV_SIZE_M)), "cells": int(cells)}

    def mask_file(self, cav: str, stem: str, mask: str) -> Path | None:
        for d in self.mask_dirs[cav]:
            p = d / f"{stem}_{MASK_FILES[mask]}.png"
            if p.is_file():
                return p
        return None

    def name_of(self, vid: int) -> str:
        return self.names.get(vid, str(vid))

    def meta(self, name: str) -> dict:
        e = self.extra
        return {"name": name, "split": self.split, "frames": len(self.timestamps), "scenario": self.folder.name,
                "source": str(self.folder), "seed": e.get("seed"), "format": "opv2v",
                "cavs": sorted(self.cav_dirs), "bev": self.bev, "range_m": float(e.get("range_m", OPV2V_RANGE_M)),
                "rate_hz": float(e.get("rate_hz", OPV2V_RATE_HZ)), "lidar_height_m": e.get("lidar_height_m"),
                "modality": e.get("modality", "camera" if self.cameras else "lidar"), "cameras": self.cameras,
                "masks": dict(self.has_masks)}


class OPV2VStore:
    """An OPV2V folder read like `FrameStore` reads a native dataset: `manifest`, `runs`, `frame(run, k)`
    (a mapping with the native frame keys) and `keys(split, ...)`. Run names are "<split folder>/<scenario>";
    frame k of a run is its k-th timestamp; a CAV is present at the timestamps it has a yaml for."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        found = find_scenarios(self.root)
        if not found:
            raise DatasetError(f"{self.root}: no OPV2V scenario folder (a folder of CAV folders named by integer "
                               "ids, with <timestamp>.yaml files, or data_protocol.yaml)")
        self._runs: dict[str, _Run] = {}
        for split, split_dir, folder in found:
            self._runs[f"{split_dir}/{folder.name}"] = _Run(self.root, split, split_dir, folder)
        self.runs = {n: r.meta(n) for n, r in self._runs.items()}
        self.manifest = {"format": "opv2v", "root": str(self.root),
                         "runs": [{k: m[k] for k in ("name", "split", "frames", "scenario", "source", "seed", "cavs")}
                                  for m in self.runs.values()]}

    def frame(self, run: str, k: int) -> OPV2VFrame:
        r = self._runs[run]
        if not 0 <= k < len(r.timestamps):
            raise DatasetError(f"{r.folder}: frame {k} out of range (0..{len(r.timestamps) - 1})")
        return OPV2VFrame(r, k)

    def keys(self, split: str, egos: str = "all", stride: int = 1) -> list:
        from v2vsim.data.torch_dataset import SampleKey

        out = []
        for name, r in self._runs.items():
            if r.split != split:
                continue
            for k in range(0, len(r.timestamps), stride):
                cavs = sorted(c for c in r.cav_dirs if r.timestamps[k] in r.stamps[c])
                out += [SampleKey(name, k, c) for c in (cavs if egos == "all" else cavs[:1])]
        return out

    def check_targets(self) -> None:
        """DatasetError when a run lacks BEV ground truth that v2vsim's samples need and that OPV2V's
        `vehicles` lists cannot give (every vehicle, road, lane)."""
        for name, r in self._runs.items():
            missing = [m for m in REQUIRED_MASKS if not r.has_masks[m]]
            if missing:
                files = ", ".join(f"<timestamp>_{MASK_FILES[m]}.png" for m in missing)
                raise DatasetError(
                    f"{r.folder}: no BEV ground truth {files} (looked in the CAV folders and in "
                    f"{self.root / 'additional' / r.split_dir / r.folder.name}): v2vsim's samples need the "
                    f"{', '.join(missing)} masks as training targets and OPV2V's yamls cannot give them. Dump them "
                    "with OpenCOOD's logreplay tool (map: save_static/save_lane/save_dynamic) or use the CoBEVT "
                    f"release's BEV maps (run {name})")


class OPV2VFrame(Mapping):
    """One frame of an OPV2V run with the keys of a native frame (v2vsim.data.layout), computed on access."""

    def __init__(self, run: _Run, k: int) -> None:
        self.r = run
        self.k = k
        self.ts = run.timestamps[k]
        self.present = sorted(c for c in run.cav_dirs if self.ts in run.stamps[c])
        self._cache: dict[str, np.ndarray] = {}

    def __enter__(self) -> OPV2VFrame:
        return self

    def __exit__(self, *exc) -> None:
        self._cache.clear()

    def close(self) -> None:
        self._cache.clear()

    def _stem(self, cav: str) -> str:
        return self.r.stamps[cav][self.ts]

    def _path(self, cav: str, suffix: str) -> Path:
        return self.r.cav_dirs[cav] / f"{self._stem(cav)}{suffix}"

    @cached_property
    def yamls(self) -> dict[str, dict]:
        return {c: load_yaml(self._path(c, ".yaml")) for c in self.present}

    def _field(self, cav: str, key: str):
        doc = self.yamls[cav]
        if key not in doc:
            raise DatasetError(f"{self._path(cav, '.yaml')}: no `{key}`")
        return doc[key]

    def pose(self, cav: str) -> tuple[float, float, float, float]:
        """The CAV's body pose: `true_ego_pos` (the vehicle; OPV2V's BEV maps are centred on it)."""
        return pose_from_carla(self._field(cav, "true_ego_pos"))

    @property
    def files(self) -> list[str]:
        keys = ["cavs", "poses", "time"]
        for c in self.present:
            keys += [f"{k}_{c}" for k in ("points", "gt", "boxes", "boxvis", "boxids", "seen")]
            if self.r.cameras:
                keys += [f"{k}_{c}" for k in ("images", "intrinsics", "extrinsics")]
        return keys

    def __iter__(self) -> Iterator[str]:
        return iter(self.files)

    def __len__(self) -> int:
        return len(self.files)

    def __contains__(self, key: object) -> bool:
        return key in self.files

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self._cache:
            self._cache[key] = self._compute(key)
        return self._cache[key]

    def _compute(self, key: str) -> np.ndarray:
        if key == "cavs":
            return np.array(self.present, dtype=str)
        if key == "poses":
            return np.array([self.pose(c) for c in self.present], dtype=np.float64).reshape(-1, 4)
        if key == "time":
            return np.float64(self.k / float(self.r.extra.get("rate_hz", OPV2V_RATE_HZ)))
        kind, _, cav = key.partition("_")
        if cav not in self.present:
            raise KeyError(key)
        if kind == "points":
            return self._points(cav)
        if kind in ("boxes", "boxvis", "boxids", "seen"):
            boxes, vis, ids, seen = self._boxes(cav)
            return {"boxes": boxes, "boxvis": vis, "boxids": ids, "seen": seen}[kind]
        if kind == "gt":
            return self._masks(cav)
        if kind in ("images", "intrinsics", "extrinsics") and self.r.cameras:
            return self._cameras(cav)[kind]
        raise KeyError(key)

    def _points(self, cav: str) -> np.ndarray:
        """LiDAR frame (CARLA axes) -> world (lidar_pose, all six degrees) -> the body frame of true_ego_pos."""
        try:
            pts = read_pcd(self._path(cav, ".pcd"))
        except (OSError, PcdError) as e:
            raise DatasetError(str(e)) from None
        lidar_to_world = carla_pose_matrix(self._field(cav, "lidar_pose"))
        world_to_body = np.linalg.inv(planar_pose_matrix(*self.pose(cav)))
        m = world_to_body @ F4 @ lidar_to_world  # CARLA LiDAR coords -> CARLA world -> v2vsim world -> body
        out = np.empty_like(pts)
        out[:, :3] = pts[:, :3].astype(np.float64) @ m[:3, :3].T + m[:3, 3]
        out[:, 3] = pts[:, 3]
        return out

    @cached_property
    def _vehicles(self) -> tuple[dict[int, tuple], dict[str, set[int]]]:
        """Every vehicle the frame's yamls place: id -> (x, y, z, yaw, l, w, h) in v2vsim's world, and each CAV's
        `vehicles` ids (what its LiDAR hit). From `vehicles`, and from our own `v2vsim` key when present (the
        CAV itself, and the vehicles on its grid no CAV saw)."""
        geo: dict[int, tuple] = {}
        listed: dict[str, set[int]] = {}
        for c in self.present:
            doc = self.yamls[c]
            listed[c] = set()
            for vid, entry in (doc.get("vehicles") or {}).items():
                geo.setdefault(int(vid), box_from_carla(entry))
                listed[c].add(int(vid))
        for c in self.present:
            extra = self.yamls[c].get(EXTRA) or {}
            if extra.get("self"):
                geo.setdefault(self.r.cav_int[c], box_from_carla(extra["self"]))
            for vid, entry in (extra.get("unseen_vehicles") or {}).items():
                geo.setdefault(int(vid), box_from_carla(entry))
        return geo, listed

    def _boxes(self, cav: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        geo, listed = self._vehicles
        union = set().union(*listed.values()) | {self.r.cav_int[c] for c in self.present}
        me = self.r.cav_int[cav]
        x, y, _, yaw = self.pose(cav)
        ids = sorted((v for v in geo if v != me), key=self.r.name_of)
        world = np.array([[geo[v][0], geo[v][1], geo[v][4], geo[v][5], geo[v][3]] for v in ids]).reshape(-1, 5)
        body = world_boxes_to_body(world, x, y, yaw)
        half = self.r.bev["size_m"] / 2
        keep = (np.abs(body[:, 0]) < half) & (np.abs(body[:, 1]) < half)
        kept = [v for v, k in zip(ids, keep, strict=True) if k]
        seen = sorted({self.r.name_of(v) for v in listed[cav]} | {cav})
        return (body[keep].astype(np.float32).reshape(-1, 5), np.array([v in union for v in kept], dtype=bool),
                np.array([self.r.name_of(v) for v in kept], dtype=str), np.array(seen, dtype=str))

    def _masks(self, cav: str) -> np.ndarray:
        from v2vsim.evaluation.gt import rasterise_boxes
        from v2vsim.world.geometry import BevGrid

        cells = self.r.bev["cells"]
        out: dict[str, np.ndarray] = {}
        for name in GT_MASKS:
            path = self.r.mask_file(cav, self._stem(cav), name)
            if path is None:
                continue
            img = np.asarray(Image.open(path).convert("L"))
            if img.shape != (cells, cells):
                raise DatasetError(f"{path}: {img.shape[1]} x {img.shape[0]} px; the run's BEV grid is "
                                   f"{cells} x {cells}")
            out[name] = img > 0
        missing = [m for m in REQUIRED_MASKS if m not in out]
        if missing:
            raise DatasetError(f"{self._path(cav, '')}_{MASK_FILES[missing[0]]}.png: missing (BEV ground truth "
                               f"{', '.join(missing)}); see OPV2VStore.check_targets")
        if "visible" not in out or "visible_self" not in out:
            # Derived from the `vehicles` lists: visible = listed by some CAV (or a CAV), visible_self = listed by
            # this CAV. Vehicles without geometry in the yamls (e.g. a CAV nobody listed) are not drawn.
            geo, listed = self._vehicles
            x, y, _, yaw = self.pose(cav)
            grid = BevGrid(self.r.bev["size_m"], cells)
            union = set().union(*listed.values()) | {self.r.cav_int[c] for c in self.present}
            own = listed[cav] | {self.r.cav_int[cav]}
            for name, ids in (("visible", union), ("visible_self", own)):
                if name in out:
                    continue
                sel = [v for v in sorted(ids) if v in geo]
                world = np.array([[geo[v][0], geo[v][1], geo[v][4], geo[v][5], geo[v][3]] for v in sel]).reshape(-1, 5)
                out[name] = rasterise_boxes(world_boxes_to_body(world, x, y, yaw), grid)
        return pack_masks(out)

    def _cameras(self, cav: str) -> dict[str, np.ndarray]:
        key = f"_cams_{cav}"
        if key not in self._cache:
            body_inv = np.linalg.inv(planar_pose_matrix(*self.pose(cav)))
            images, intr, extr = [], [], []
            for i in range(CAMERAS):
                path = self._path(cav, f"_camera{i}.png")
                if not path.is_file():
                    raise DatasetError(f"{path}: missing (the run has camera images)")
                images.append(np.asarray(Image.open(path).convert("RGB")))
                cam = self._field(cav, f"camera{i}")
                intr.append(intrinsic_from_carla(cam["intrinsic"]))
                extr.append(body_inv @ camera_from_cords(cam["cords"]))
            if len({im.shape for im in images}) != 1:
                raise DatasetError(f"{self._path(cav, '_camera*.png')}: the four images differ in size")
            self._cache[key] = {"images": np.stack(images), "intrinsics": np.stack(intr).astype(np.float32),
                                "extrinsics": np.stack(extr).astype(np.float32)}
        return self._cache[key]

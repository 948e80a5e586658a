"""Reading the OPV2V layout (v2vsim.data.opv2v_layout): `OPV2VStore(root)` reads such a folder (ours, written by
v2vsim.data.opv2v_write, or OPV2V itself) into the frames `FrameStore` (v2vsim.data.store) gives for a native
dataset (same keys, v2vsim's frames and units), so `CooperativeDataset` and `v2vsim train` take either
(v2vsim.data.torch_dataset.open_store tells them apart with `is_opv2v`). docs/dataset.md, "OPV2V format", has the
conversion table and what is derived or absent.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from functools import cached_property
from pathlib import Path

import numpy as np
from PIL import Image

from v2vsim.data.carla_frames import (
    F4,
    box_from_carla,
    camera_from_cords,
    carla_pose_matrix,
    intrinsic_from_carla,
    planar_pose_matrix,
    pose_from_carla,
    world_boxes_to_body,
)
from v2vsim.data.layout import GT_MASKS, DatasetError, pack_masks
from v2vsim.data.opv2v_layout import (
    CAMERAS,
    CAV_DIR,
    DIR_SPLITS,
    EXTRA,
    MASK_FILES,
    OPV2V_BEV_SIZE_M,
    OPV2V_RANGE_M,
    OPV2V_RATE_HZ,
    PROTOCOL,
    REQUIRED_MASKS,
    STEM,
    load_yaml,
)
from v2vsim.data.pcd import PcdError, read_pcd
from v2vsim.data.store import SampleKey


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

    def keys(self, split: str, egos: str = "all", stride: int = 1) -> list[SampleKey]:
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

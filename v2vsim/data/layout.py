"""On-disk layout of a v2vsim dataset (docs/dataset.md): one folder per recorded run, one
compressed .npz per frame, a manifest at the top.

    DIR/manifest.json                       runs, splits, format version
    DIR/<scenario>_s<seed>/run.json         the run's scenario (as loaded), CAV ids, BEV grid
    DIR/<scenario>_s<seed>/f<frame:05d>.npz one frame (keys below)

Frame keys (`cav` = a CAV id present in that frame):
    cavs            [N] str      CAVs present, in id order
    poses           [N, 4] f64   world pose (x, y, z, yaw) of each, same order
    time            f64          simulated seconds since frame 0
    points_<cav>    [P, 4] f16   LiDAR x, y, z, intensity in the CAV's body frame (z up from the ground)
    gt_<cav>        [5, S*S/8] u8  packed bit masks on that CAV's BEV grid, order GT_MASKS
    boxes_<cav>     [K, 5] f32   GT boxes (x, y, l, w, yaw) in that CAV's body frame (the CAV itself left out)
    boxvis_<cav>    [K] bool     box is visible to some CAV (the scored set)
    boxids_<cav>    [K] str      actor id of each box
    seen_<cav>      [V] str      vehicle ids this CAV's own sensors saw
    images_<cav>    [4, h, w, 3] u8, intrinsics_<cav> [4, 3, 3], extrinsics_<cav> [4, 4, 4]  (cameras only)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FORMAT = "v2vsim-dataset"
VERSION = 1
SPLITS = ("train", "val", "eval")
# dynamic: every vehicle; visible: vehicles any CAV saw (the scored target); road; lane;
# visible_self: vehicles this CAV's own sensors saw (the single-agent training target).
GT_MASKS = ("dynamic", "visible", "road", "lane", "visible_self")


class DatasetError(Exception):
    """A dataset problem a user can fix: the message names the file and what is wrong."""


def run_name(scenario: str, seed: int) -> str:
    return f"{scenario}_s{seed}"


def frame_path(run_dir: Path, frame: int) -> Path:
    return run_dir / f"f{frame:05d}.npz"


def pack_masks(masks: dict[str, np.ndarray]) -> np.ndarray:
    """{name: [S, S] bool} -> [len(GT_MASKS), S*S/8] uint8."""
    return np.stack([np.packbits(masks[k].reshape(-1)) for k in GT_MASKS])


def unpack_masks(packed: np.ndarray, cells: int) -> dict[str, np.ndarray]:
    """Inverse of pack_masks."""
    bits = np.unpackbits(packed, axis=1, count=cells * cells).astype(bool)
    return {k: bits[i].reshape(cells, cells) for i, k in enumerate(GT_MASKS)}


@dataclass(frozen=True)
class RunEntry:
    """One recorded run in the manifest."""

    name: str
    scenario: str  # scenario name
    source: str  # scenario YAML it came from
    seed: int
    split: str
    frames: int
    cavs: int
    background_per_hour: float
    overrides: tuple[str, ...]

    def to_json(self) -> dict:
        return {**self.__dict__, "overrides": list(self.overrides)}


def read_manifest(root: Path) -> dict:
    """The manifest of dataset `root`; DatasetError when it is missing or not ours."""
    path = root / "manifest.json"
    if not path.is_file():
        raise DatasetError(f"{path}: no dataset manifest (make one with `v2vsim dataset`)")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from None
    if doc.get("format") != FORMAT or doc.get("version") != VERSION:
        raise DatasetError(f"{path}: format {doc.get('format')!r} v{doc.get('version')}; "
                           f"this v2vsim reads {FORMAT!r} v{VERSION}")
    return doc


def runs_of(doc: dict, split: str) -> list[dict]:
    return [r for r in doc["runs"] if r["split"] == split]


def check_disjoint(doc: dict, scenario: str, seeds: list[int], split: str, path: Path) -> None:
    """Seeds of one scenario may appear in one split only (train / val / eval never share a run)."""
    for r in doc["runs"]:
        if r["scenario"] == scenario and r["seed"] in seeds and r["split"] != split:
            raise DatasetError(f"{path}: seed {r['seed']} of scenario {scenario!r} is already in split "
                               f"{r['split']!r}; splits must use disjoint seeds")

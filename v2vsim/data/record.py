"""`v2vsim dataset`: record runs of a scenario as a dataset (layout in v2vsim.data.layout).

Every frame of every seed: each CAV senses exactly as its agent process would (same sensor
seeds), and ground truth is rasterised with every CAV as the ego. Deterministic per seed: the
traffic, the sensor noise and hence every byte of a frame follow from (scenario, seed).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from v2vsim.config import Scenario, load_scenario
from v2vsim.data.layout import (
    FORMAT,
    SPLITS,
    VERSION,
    DatasetError,
    RunEntry,
    check_disjoint,
    frame_path,
    pack_masks,
    read_manifest,
    run_name,
)
from v2vsim.gt import bev_ground_truth, gt_boxes, visible_actor_ids
from v2vsim.perception import body_frame_points
from v2vsim.sensing import sense
from v2vsim.sensors.scene import build_map_assets, build_scene
from v2vsim.traffic import make_backend
from v2vsim.world import WorldState


def parse_seeds(text: str) -> list[int]:
    """'A-B' (inclusive) or 'A,B,C' -> seeds; ValueError with what is allowed."""
    try:
        if "-" in text.strip("-"):
            a, b = text.split("-", 1)
            seeds = list(range(int(a), int(b) + 1))
        else:
            seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ValueError(f"--seeds {text!r}: expected A-B or A,B,C with non-negative integers") from None
    if not seeds or min(seeds) < 0:
        raise ValueError(f"--seeds {text!r}: expected A-B (A <= B) or A,B,C with non-negative integers")
    return seeds


def record_frame(world: WorldState, sc: Scenario, assets: object, cameras: bool) -> dict[str, np.ndarray]:
    """One frame's arrays (keys as in v2vsim.data.layout)."""
    scene = build_scene(world, assets)
    lidar_track = sc.perception.modality == "lidar"
    cavs = sorted(a.id for a in world.cavs)
    sensed = {c: sense(world, c, sc, scene, lidar=True, cameras=cameras or not lidar_track) for c in cavs}
    # Visibility from the sensors of the scenario's modality, as the CAV agents report it in a run.
    seen = {c: visible_actor_ids([s.lidar] if lidar_track else [], [] if lidar_track else [s.cameras], world)
            for c, s in sensed.items()}
    union = frozenset().union(*seen.values()) if seen else frozenset()
    out: dict[str, np.ndarray] = {
        "cavs": np.array(cavs, dtype=str),
        "poses": np.array([world.actor(c).pose.as_tuple() for c in cavs], dtype=np.float64).reshape(-1, 4),
        "time": np.float64(world.time),
    }
    for c, sf in sensed.items():
        gt = bev_ground_truth(world, c, sc.bev, union, assets=assets, more_visible={"visible_self": seen[c]})
        boxes, ids = gt_boxes(world, c, sc.bev)
        out[f"points_{c}"] = body_frame_points(sf, sc).astype(np.float16)
        out[f"gt_{c}"] = pack_masks(gt)
        out[f"boxes_{c}"] = boxes.astype(np.float32).reshape(-1, 5)
        out[f"boxvis_{c}"] = np.array([i in union for i in ids], dtype=bool)
        out[f"boxids_{c}"] = np.array(ids, dtype=str)
        out[f"seen_{c}"] = np.array(sorted(seen[c]), dtype=str)
        if sf.cameras is not None:
            out[f"images_{c}"] = sf.cameras.images
            out[f"intrinsics_{c}"] = sf.cameras.rig.intrinsics.astype(np.float32)
            out[f"extrinsics_{c}"] = sf.cameras.rig.extrinsics.astype(np.float32)
    return out


def _git_commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                              cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def _write_manifest(root: Path, doc: dict) -> None:
    tmp = root / "manifest.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(root / "manifest.json")


def record_dataset(scenario_path: str, seeds: list[int], frames: int, out: Path, split: str = "train",
                   overrides: tuple[str, ...] = (), cameras: bool = False, log=sys.stderr) -> Path:
    """Record `frames` frames of every seed into `out`, adding the runs to its manifest.

    A run already complete in the manifest is skipped (so a command can be re-run to resume)."""
    if split not in SPLITS:
        raise DatasetError(f"--split {split!r}: allowed: {', '.join(SPLITS)}")
    if frames < 1:
        raise DatasetError(f"--frames {frames}: must be >= 1")
    out.mkdir(parents=True, exist_ok=True)
    base = load_scenario(scenario_path, overrides)
    doc = read_manifest(out) if (out / "manifest.json").exists() else {
        "format": FORMAT, "version": VERSION, "runs": [], "created_with": {"git_commit": _git_commit()}}
    check_disjoint(doc, base.name, seeds, split, out / "manifest.json")
    done = {(r["scenario"], r["seed"]) for r in doc["runs"]}
    todo = [s for s in seeds if (base.name, s) not in done]
    total = len(todo) * frames
    t0, n = time.monotonic(), 0
    for seed in todo:
        sc = load_scenario(scenario_path, (*overrides, f"seed={seed}"))
        run_dir = out / run_name(sc.name, seed)
        run_dir.mkdir(parents=True, exist_ok=True)
        recorded = 0
        with make_backend(sc) as backend:
            world = backend.reset()
            assets = build_map_assets(backend.static)
            for k in range(frames):
                if k > 0:
                    world = backend.step()
                if not world.cavs:
                    break
                arrays = record_frame(world, sc, assets, cameras)
                tmp = run_dir / f".f{k:05d}.tmp.npz"
                np.savez_compressed(tmp, **arrays)
                tmp.replace(frame_path(run_dir, k))
                recorded += 1
                n += 1
                el = time.monotonic() - t0
                rate = n / el if el > 0 else 0.0
                eta = (total - n) / rate if rate > 0 else 0.0
                print(f"\rdataset {sc.name} seed {seed}: frame {k + 1}/{frames}  {n}/{total} frames  "
                      f"{rate:.1f} frames/s  ETA {eta:.0f} s   ", end="", file=log, flush=True)
        (run_dir / "run.json").write_text(json.dumps({
            "scenario": sc.name, "source": str(sc.source), "seed": seed, "frames": recorded,
            "cavs": [f"cav{i}" for i in range(sc.cavs.count)], "bev": {"size_m": sc.bev.size_m, "cells": sc.bev.cells},
            "range_m": sc.comm.range_m, "rate_hz": sc.rate_hz, "lidar_height_m": sc.sensors.lidar.height_m,
            "modality": sc.perception.modality, "cameras": cameras, "overrides": list(sc.overrides)}, indent=1))
        entry = RunEntry(run_dir.name, sc.name, str(sc.source), seed, split, recorded, sc.cavs.count,
                         sc.traffic.background_per_hour, tuple(overrides))
        doc["runs"].append(entry.to_json())
        _write_manifest(out, doc)
    print(file=log)
    return out

"""`v2vsim dataset`: record runs of a scenario as a dataset (layout in v2vsim.data.layout).

Every frame of every seed: each CAV senses exactly as its agent process would (same sensor
seeds), and ground truth is rasterised with every CAV as the ego. Deterministic per seed: the
traffic, the sensor noise and hence every byte of a frame follow from (scenario, seed).
"""

from __future__ import annotations

import gzip
import json
import multiprocessing
import re
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from models import zoo
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
from v2vsim.evaluation.gt import bev_ground_truth, gt_boxes, visible_actor_ids
from v2vsim.perception.encode import body_frame_points
from v2vsim.sensors.scene import build_map_assets, build_scene
from v2vsim.sensors.sensing import sense
from v2vsim.traffic import make_backend
from v2vsim.world.serialize import static_from_bytes, static_to_bytes, world_from_bytes, world_to_bytes
from v2vsim.world.state import WorldState


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


TRAFFIC_DIR = "traffic"  # <run>/traffic/: static.npz + worlds.jsonl.gz (v2vsim.world.serialize, no pickle)


def record_traffic(sc: Scenario, frames: int, run_dir: Path) -> list[WorldState]:
    """Step the scenario's traffic backend for up to `frames` ticks (fewer if every CAV has left) and
    save the world states under `run_dir`/traffic, so that sensing can be (re)done without the simulator."""
    worlds: list[WorldState] = []
    with make_backend(sc) as backend:
        world = backend.reset()
        for k in range(frames):
            if k > 0:
                world = backend.step()
            if not world.cavs:
                break
            worlds.append(world)
        static = backend.static
    folder = run_dir / TRAFFIC_DIR
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "static.npz").write_bytes(static_to_bytes(static))
    tmp = folder / "worlds.jsonl.gz.tmp"
    with gzip.open(tmp, "wb") as f:
        for w in worlds:
            f.write(world_to_bytes(w) + b"\n")
    tmp.replace(folder / "worlds.jsonl.gz")
    (folder / "traffic.json").write_text(json.dumps({"seed": sc.seed, "frames_asked": frames,
                                                     "frames": len(worlds), "overrides": list(sc.overrides)}))
    return worlds


def load_traffic(run_dir: Path, frames: int, overrides: tuple[str, ...]) -> list[WorldState] | None:
    """The world states `record_traffic` saved for this run and request, or None when there are none."""
    folder = run_dir / TRAFFIC_DIR
    meta_path = folder / "traffic.json"
    if not meta_path.is_file():
        return None
    meta = json.loads(meta_path.read_text())
    if meta.get("frames_asked") != frames or meta.get("overrides") != list(overrides):
        return None  # recorded for another request: simulate again
    try:
        static = static_from_bytes((folder / "static.npz").read_bytes())
        with gzip.open(folder / "worlds.jsonl.gz", "rb") as f:
            worlds = [world_from_bytes(line, static) for line in f if line.strip()]
    except (OSError, ValueError) as e:
        raise DatasetError(f"{folder}: recorded traffic unreadable ({e}); delete the folder to simulate again"
                           ) from None
    if len(worlds) != meta.get("frames"):
        raise DatasetError(f"{folder}: {len(worlds)} world states, traffic.json says {meta.get('frames')}; "
                           "delete the folder to simulate again")
    return worlds


def _run_traffic(scenario_path: str, seed: int, frames: int, out: Path, overrides: tuple[str, ...]
                 ) -> tuple[Scenario, Path, list[WorldState]]:
    """A seed's scenario, run folder and world states: recorded earlier under the run folder, or simulated now."""
    sc = load_scenario(scenario_path, (*overrides, f"seed={seed}"))
    run_dir = out / run_name(sc.name, seed)
    run_dir.mkdir(parents=True, exist_ok=True)
    worlds = load_traffic(run_dir, frames, sc.overrides)
    if worlds is None:
        worlds = record_traffic(sc, frames, run_dir)
    return sc, run_dir, worlds


SENSING_FILE = "sensing.json"  # <run>/sensing.json: what the frames on disk were sensed with


def _prepare_sensing(run_dir: Path, cameras: bool, overrides: tuple[str, ...]) -> int:
    """Before sensing a run: frames already written with the same settings and traffic (an interrupted command
    run again) are kept and skipped; frames of other settings are removed. Returns the frames kept."""
    traffic = run_dir / TRAFFIC_DIR / "traffic.json"
    want = {"cameras": cameras, "overrides": list(overrides),
            "traffic": json.loads(traffic.read_text()) if traffic.is_file() else None}
    marker = run_dir / SENSING_FILE
    try:
        same = json.loads(marker.read_text()) == want
    except (OSError, ValueError):
        same = False
    frames = sorted(run_dir.glob("f[0-9][0-9][0-9][0-9][0-9].npz"))
    if not same:
        for f in frames:
            f.unlink()
        marker.write_text(json.dumps(want))
        return 0
    return len(frames)


def _sense_frames(sc: Scenario, run_dir: Path, worlds: list[WorldState], ks: range, cameras: bool,
                  progress=None) -> None:
    """Sense and write frames `ks` of a run, skipping those already written (kept by _prepare_sensing).
    `progress(k)` is called after each frame written or found."""
    assets = None
    for k in ks:
        if frame_path(run_dir, k).is_file():
            if progress is not None:
                progress(k)
            continue
        assets = assets or build_map_assets(worlds[0].static)
        arrays = record_frame(worlds[k], sc, assets, cameras)
        tmp = run_dir / f".f{k:05d}.tmp.npz"
        np.savez_compressed(tmp, **arrays)
        tmp.replace(frame_path(run_dir, k))
        if progress is not None:
            progress(k)


def _write_run_json(sc: Scenario, run_dir: Path, frames: int, cameras: bool) -> None:
    (run_dir / "run.json").write_text(json.dumps({
        "scenario": sc.name, "source": str(sc.source), "seed": sc.seed, "frames": frames,
        "cavs": [f"cav{i}" for i in range(sc.cavs.count)], "bev": {"size_m": sc.bev.size_m, "cells": sc.bev.cells},
        "range_m": sc.comm.range_m, "rate_hz": sc.rate_hz, "lidar_height_m": sc.sensors.lidar.height_m,
        "modality": sc.perception.modality, "cameras": cameras, "overrides": list(sc.overrides),
        "inputs": scenario_inputs(sc)}, indent=1))


def scenario_inputs(sc: Scenario) -> dict[str, str]:
    """{"net": sha256, "buildings": sha256} of the files the run's world was built from (what the benchmark-network
    exclusion compares, v2vsim/training/held_out.py); a file the scenario does not name is left out."""
    out = {}
    for key in ("net", "buildings"):
        path = getattr(sc.traffic, key)
        if path is not None:
            out[key] = zoo.sha256(Path(path))
    return out


def record_run(scenario_path: str, seed: int, frames: int, out: Path, overrides: tuple[str, ...] = (),
               cameras: bool = False, traffic_only: bool = False, progress=None) -> int:
    """One seed: its traffic (recorded earlier under the run folder, or simulated now), then with
    `traffic_only` False every frame sensed and written. Returns the frames recorded.
    `progress(k)` is called after each frame written."""
    sc, run_dir, worlds = _run_traffic(scenario_path, seed, frames, out, overrides)
    if traffic_only:
        return len(worlds)
    _prepare_sensing(run_dir, cameras, sc.overrides)
    _sense_frames(sc, run_dir, worlds, range(len(worlds)), cameras, progress)
    _write_run_json(sc, run_dir, len(worlds), cameras)
    return len(worlds)


def _traffic_job(job: tuple) -> tuple[int, int]:
    scenario_path, seed, frames, out, overrides = job
    return seed, len(_run_traffic(scenario_path, seed, frames, out, overrides)[2])


def _sense_job(job: tuple) -> tuple[int, int]:
    """Frames lo..hi-1 of one seed's recorded traffic, in a worker process (one torch thread)."""
    import torch

    torch.set_num_threads(1)
    scenario_path, seed, frames, out, overrides, cameras, lo, hi = job
    sc, run_dir, worlds = _run_traffic(scenario_path, seed, frames, out, overrides)
    _sense_frames(sc, run_dir, worlds, range(lo, min(hi, len(worlds))), cameras)
    return seed, min(hi, len(worlds)) - lo


RUN_DIR = re.compile(r".+_s[0-9]+")  # run_name(scenario, seed)
SENSE_CHUNK = 25  # frames per parallel sensing task: each task builds the map assets once


def check_dataset_folder(out: Path) -> None:
    """`out` is new, empty, a dataset (manifest.json) or holds only run folders (a --traffic-only call's):
    anything else is refused rather than getting a manifest among unrelated files."""
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out}: is a file, not a folder")
    if not out.is_dir() or (out / "manifest.json").exists():
        return
    other = sorted(p.name for p in out.iterdir() if not (p.is_dir() and RUN_DIR.fullmatch(p.name)))
    if other:
        raise DatasetError(f"--out {out}: not empty and not a dataset (no manifest.json; it holds "
                           f"{', '.join(other[:3])}{', ...' if len(other) > 3 else ''}); use a new or empty folder")


def record_dataset(scenario_path: str, seeds: list[int], frames: int, out: Path, split: str = "train",
                   overrides: tuple[str, ...] = (), cameras: bool = False, log=sys.stderr,
                   traffic_only: bool = False, jobs: int = 1) -> Path:
    """Record `frames` frames of every seed into `out`, adding the runs to its manifest.

    A run already complete in the manifest is skipped (so a command can be re-run to resume).
    `traffic_only`: only simulate and save each run's traffic (no sensing, no manifest entry); a later
    call senses from it without the simulator (e.g. on a machine without SUMO). `jobs` > 1 spreads the
    seeds' traffic, then their frames in chunks of SENSE_CHUNK, over that many processes."""
    if split not in SPLITS:
        raise DatasetError(f"--split {split!r}: allowed: {', '.join(SPLITS)}")
    if frames < 1:
        raise DatasetError(f"--frames {frames}: must be >= 1")
    if jobs < 1:
        raise DatasetError(f"--jobs {jobs}: must be >= 1")
    check_dataset_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    base = load_scenario(scenario_path, overrides)
    doc = read_manifest(out) if (out / "manifest.json").exists() else {
        "format": FORMAT, "version": VERSION, "runs": [], "created_with": {"git_commit": _git_commit()}}
    check_disjoint(doc, base.name, seeds, split, out / "manifest.json")
    done = {(r["scenario"], r["seed"]) for r in doc["runs"]}
    todo = [s for s in seeds if (base.name, s) not in done]
    total = len(todo) * frames
    t0, n = time.monotonic(), 0

    def show(what: str) -> None:
        el = time.monotonic() - t0
        rate = n / el if el > 0 else 0.0
        eta = (total - n) / rate if rate > 0 else 0.0
        print(f"\rdataset {base.name} {what}  {n}/{total} frames  {rate:.1f} frames/s  ETA {eta:.0f} s   ",
              end="", file=log, flush=True)

    def finished(seed: int, recorded: int) -> None:
        if traffic_only:
            return
        # the seed does not change traffic density: the base scenario's is the run's
        entry = RunEntry(run_name(base.name, seed), base.name, str(base.source), seed, split, recorded,
                         base.cavs.count, base.traffic.background_per_hour, tuple(overrides))
        doc["runs"].append(entry.to_json())
        _write_manifest(out, doc)

    if jobs == 1:
        for seed in todo:
            def tick(k: int, seed: int = seed) -> None:
                nonlocal n
                n += 1
                show(f"seed {seed}: frame {k + 1}/{frames}")

            recorded = record_run(scenario_path, seed, frames, out, overrides, cameras, traffic_only,
                                  progress=tick)
            if traffic_only:
                n += frames
                show(f"seed {seed}: traffic")
            finished(seed, recorded)
    else:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(jobs, mp_context=ctx) as pool:
            # traffic first (one process per seed), then the frames of every seed in chunks across the pool
            lengths = dict(pool.map(_traffic_job, [(scenario_path, s, frames, out, overrides) for s in todo]))
            if traffic_only:
                n = total
                show("traffic")
            else:
                total = sum(lengths.values())
                for s in todo:  # keep what an interrupted call wrote with the same settings
                    sc = load_scenario(scenario_path, (*overrides, f"seed={s}"))
                    _prepare_sensing(out / run_name(sc.name, s), cameras, sc.overrides)
                jobs_ = [(scenario_path, s, frames, out, overrides, cameras, lo, lo + SENSE_CHUNK)
                         for s in todo for lo in range(0, lengths[s], SENSE_CHUNK)]
                for fut in as_completed([pool.submit(_sense_job, j) for j in jobs_]):
                    seed, done_frames = fut.result()
                    n += done_frames
                    show(f"seed {seed} chunk done")
        for seed in todo:  # manifest in seed order, whatever order the workers finished in
            if not traffic_only:
                sc = load_scenario(scenario_path, (*overrides, f"seed={seed}"))
                _write_run_json(sc, out / run_name(sc.name, seed), lengths[seed], cameras)
            finished(seed, lengths[seed])
    print(file=log)
    return out

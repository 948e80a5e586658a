"""`v2vsim frame`: one frame written as files (DESIGN.md "Command line"), for looking at what CAVs sense."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from v2vsim.config import ConfigError, Scenario
from v2vsim.evaluation.gt import bev_ground_truth, visible_actor_ids
from v2vsim.sensors.scene import build_map_assets, build_scene
from v2vsim.sensors.sensing import ego_ids, sense
from v2vsim.traffic import make_backend


def write_frame(scenario: Scenario, at_s: float, out: Path) -> list[Path]:
    if at_s < 0 or at_s > scenario.duration_s:
        raise ConfigError(f"--at {at_s}: outside the scenario's 0..{scenario.duration_s} s (duration_s)")
    out.mkdir(parents=True, exist_ok=True)
    target = round(at_s * scenario.rate_hz)
    with make_backend(scenario) as backend:
        world = backend.reset()
        while world.frame < target:
            world = backend.step()
        static = backend.static
    assets = build_map_assets(static)
    scene = build_scene(world, assets)
    written: list[Path] = []

    def save(path: Path) -> Path:
        written.append(path)
        return path

    (save(out / "world.json")).write_text(json.dumps(world.to_json(), indent=1))
    frames = []
    cavs = [a.id for a in world.cavs]
    for cid in cavs:
        sf = sense(world, cid, scenario, scene)
        frames.append(sf)
        np.save(save(out / f"cav_{cid}_lidar.npy"), sf.lidar.points.astype(np.float32))
        for k in range(sf.cameras.images.shape[0]):
            Image.fromarray(sf.cameras.images[k]).save(save(out / f"cav_{cid}_cam{k}.png"))
        (save(out / f"cav_{cid}_cameras.json")).write_text(json.dumps(sf.cameras.rig.to_json(), indent=1))
    egos = ego_ids(scenario, cavs)
    if egos:
        visible = visible_actor_ids([f.lidar for f in frames], [f.cameras for f in frames], world)
        gt = bev_ground_truth(world, egos[0], scenario.bev, visible, assets=assets)
        for name in ("dynamic", "visible", "road", "lane"):
            Image.fromarray(gt[name].astype(np.uint8) * 255).save(save(out / f"gt_{name}.png"))
    return written

"""The frames line up end to end: a neighbour's ground truth, warped into the ego's BEV grid with the
relative pose the ego fusion process uses, matches the ego's own ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from models.warp import warp_to_ego
from v2vsim.config import load_scenario
from v2vsim.evaluation.gt import bev_ground_truth
from v2vsim.sensors.scene import build_map_assets
from v2vsim.traffic import make_backend
from v2vsim.world.geometry import relative_pose

SCENARIO = Path(__file__).resolve().parents[2] / "scenarios" / "intersection.yaml"


def test_neighbour_ground_truth_warps_onto_ego_ground_truth() -> None:
    sc = load_scenario(SCENARIO)
    with make_backend(sc) as backend:
        world = backend.reset()
        for _ in range(60):
            world = backend.step()
        assets = build_map_assets(backend.static)
    ego = world.actor("cav0")
    checked = 0
    for other in world.cavs[1:]:
        dx, dy, dyaw = relative_pose(ego.pose, other.pose)
        if np.hypot(dx, dy) > 60:
            continue
        mine = bev_ground_truth(world, "cav0", sc.bev, (), assets=assets)
        theirs = bev_ground_truth(world, other.id, sc.bev, (), assets=assets)
        stack = torch.from_numpy(np.stack([theirs["road"], theirs["dynamic"]]).astype(np.float32))[None]
        warped, valid = warp_to_ego(stack, torch.tensor([[dx, dy, dyaw]], dtype=torch.float32), sc.bev.size_m)
        valid = valid[0].numpy()
        road = warped[0, 0].numpy() >= 0.5
        cars = warped[0, 1].numpy() >= 0.5
        assert valid.mean() > 0.2
        agree = (road == mine["road"])[valid].mean()
        assert agree > 0.97, (other.id, agree)
        inter = (cars & mine["dynamic"] & valid).sum()
        union = ((cars | mine["dynamic"]) & valid).sum()
        assert inter / union > 0.8, (other.id, inter / union)
        checked += 1
    assert checked >= 1

"""A mixed fleet's pieces (v2vsim.perception.fleet, .build): each CAV's type, the methods an ego of a type can run,
the space a message names, and the fusion contract on mixed inputs: LiDAR and aligned camera maps fused together,
an absent agent ignored bit for bit, by every intermediate method the base zoo ships."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.aligner import AlignedEncoder
from models.registry import is_intermediate
from tests.v2vsim.perception._clouds import cloud
from v2vsim.config import load_scenario
from v2vsim.perception.aligned import build_cav_encoder, feature_space, space_label
from v2vsim.perception.build import build_method_models
from v2vsim.perception.encode import encode_points
from v2vsim.perception.fleet import AgentType, agent_type, extra_types
from v2vsim.perception.plan import plan_models, runnable_methods
from v2vsim.recording.world3d import cav_colour

MIXED = "scenarios/intersection_mixed.yaml"


def test_types_methods_and_spaces() -> None:
    sc = load_scenario(MIXED)
    assert agent_type(sc, "cav0") == AgentType("lidar", "pointpillars")
    assert agent_type(sc, "cav3") == AgentType("camera", "sinbevt") and extra_types(sc) == [AgentType("camera",
                                                                                                      "sinbevt")]
    assert "early" in runnable_methods(sc)  # a LiDAR ego merges the LiDAR CAVs' clouds
    cam_ego = load_scenario(MIXED, ["cavs.fleet=[{cavs: [cav0]}]"])
    assert "early" not in runnable_methods(cam_ego)
    plan = plan_models(sc)
    space = feature_space(plan)
    assert space.startswith("pointpillars_tiny:") and len(space.split(":")[1]) == 12
    assert space_label(plan, "cav2") == f"sinbevt@{space}" and space_label(plan, "cav0") == f"pointpillars@{space}"
    single = plan_models(load_scenario("scenarios/intersection.yaml"))
    assert space_label(single, "cav2") == ""  # no fleet: nothing on the wire


def test_mixed_inputs_keep_the_fusion_contract() -> None:
    """For each intermediate method of the shipped base: the ego's LiDAR map, an aligned camera map, an absent slot
    and another LiDAR map fused; garbage (NaN, inf) in the absent slot leaves the fused map bit for bit unchanged,
    and the camera map changes it (it is fused, not ignored)."""
    sc = load_scenario(MIXED)
    plan = plan_models(sc)
    lidar, camera = build_cav_encoder(plan, "cav0"), build_cav_encoder(plan, "cav2")
    assert isinstance(camera, AlignedEncoder)
    rng = np.random.default_rng(0)
    with torch.no_grad():
        cam = camera(torch.from_numpy(rng.random((1, 4, 3, 150, 200), dtype=np.float32)),
                     torch.tensor([[[100.0, 0, 100], [0, 100.0, 75], [0, 0, 1]]]).expand(1, 4, 3, 3),
                     torch.eye(4).expand(1, 4, 4, 4))[0]
    maps = [torch.from_numpy(encode_points(lidar, cloud(0))), cam, torch.zeros_like(cam),
            torch.from_numpy(encode_points(lidar, cloud(1)))]
    feats = torch.stack(maps)[None]  # [1, 4, C, F, F]
    rel = torch.tensor([[[0.0, 0, 0], [12.0, -3, 0.4], [0, 0, 0], [-20.0, 5, -1.2]]])
    valid = torch.tensor([[True, True, False, True]])
    garbage = feats.clone()
    garbage[0, 2] = float("nan")
    garbage[0, 2, :, :3] = float("inf")
    no_cam = feats.clone()
    no_cam[0, 1] = 0.0
    methods = tuple(m for m in runnable_methods(sc) if is_intermediate(m))
    assert methods == ("attfuse", "fcooper", "v2vnet", "disconet", "cobevt")
    for m, model in build_method_models(plan, lidar, methods).items():
        with torch.no_grad():
            a, b = model.fuse(feats, rel, valid), model.fuse(garbage, rel, valid)
            c = model.fuse(no_cam, rel, valid)
        assert torch.isfinite(a).all() and torch.equal(a, b), m
        assert not torch.equal(a, c), m


@pytest.mark.parametrize("cavs", [["cav0", "cav1", "cav2", "cav3"]])
def test_recording_colours_by_type(cavs: list[str]) -> None:
    types = {"cav0": "LiDAR (pointpillars)", "cav1": "LiDAR (pointpillars)", "cav2": "camera (sinbevt)",
             "cav3": "camera (lara)"}
    c = {cav: cav_colour(cavs, cav, types) for cav in cavs}
    assert c["cav0"] == c["cav1"] and len({c["cav1"], c["cav2"], c["cav3"]}) == 3
    assert len({cav_colour(cavs, cav) for cav in cavs}) == 4  # no fleet: one colour per CAV, as before

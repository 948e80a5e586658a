"""The ego side of learned latency compensation: only late neighbours with a message before are extrapolated,
by their age in message intervals; an aligned message (age 0) is left exactly as it is."""

from __future__ import annotations

import numpy as np
import torch

from models.extrapolation import FeatureExtrapolation
from v2vsim.perception.extrapolate import extrapolate_features
from v2vsim.perception.fuse import FusionInputs


def _inputs(ages: dict[str, float]) -> FusionInputs:
    rng = np.random.default_rng(0)
    feats = {s: rng.standard_normal((4, 8, 8)).astype(np.float32) for s in ("cav0", "cav1", "cav2")}
    inp = FusionInputs(senders=["cav0", "cav1", "cav2"], rel_poses=np.zeros((3, 3), np.float32), features=feats)
    for s, age in ages.items():
        inp.feature_ages[s] = age
        inp.previous_features[s] = (feats[s] - 0.5, np.zeros(3, np.float32), 0.1)  # 100 ms before
    return inp


def test_only_late_neighbours_are_extrapolated_by_their_age() -> None:
    torch.manual_seed(0)
    module = FeatureExtrapolation(4).eval()
    torch.nn.init.normal_(module.net[-1].weight, std=0.1)  # as if trained: D != 0
    inp = _inputs({"cav1": 0.2, "cav2": 0.0})
    out = extrapolate_features(module, inp, bev_size_m=100.0)
    assert set(out) == {"cav1"}  # cav2 was fused aligned; cav0 (the ego) has no previous message
    with torch.no_grad():
        new = torch.from_numpy(inp.features["cav1"])[None]
        d = module.derivative(new, torch.from_numpy(inp.previous_features["cav1"][0])[None])[0].numpy()
    np.testing.assert_allclose(out["cav1"], inp.features["cav1"] + 2.0 * d, rtol=1e-5, atol=1e-5)  # 200 ms / 100 ms


def test_an_untrained_module_changes_nothing() -> None:
    out = extrapolate_features(FeatureExtrapolation(4).eval(), _inputs({"cav1": 0.3}), bev_size_m=100.0)
    np.testing.assert_array_equal(out["cav1"], _inputs({"cav1": 0.3}).features["cav1"])

"""perception.precision: bfloat16 autocast reaches the models and nothing else (every output float32)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.build import build_cooperative
from tests.v2vsim.perception._clouds import cloud
from v2vsim.config import ConfigError, load_scenario
from v2vsim.perception import precision as P
from v2vsim.perception.encode import encode_points, late_outputs
from v2vsim.perception.fuse import FusionInputs, predict


def test_auto_follows_the_cpu_and_a_bad_value_is_named(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setattr(P, "native_bf16", lambda: True)
    assert P.resolve("auto") == "bf16" and P.resolve("fp32") == "fp32"
    monkeypatch.setattr(P, "native_bf16", lambda: False)
    assert P.resolve("auto") == "fp32" and P.resolve("bf16") == "bf16"
    with pytest.raises(ConfigError, match="perception.precision"):
        load_scenario("scenarios/intersection.yaml", ["perception.precision=fp16"])


def test_bf16_changes_the_models_numbers_a_little_and_every_output_stays_float32() -> None:
    torch.manual_seed(0)
    model = build_cooperative("pointpillars", "cobevt", "tiny").eval()
    feats = {p: encode_points(model.encoder, cloud(), p) for p in ("fp32", "bf16")}
    assert feats["bf16"].dtype == np.float32 and feats["bf16"].shape == feats["fp32"].shape
    scale = np.abs(feats["fp32"]).max()
    assert 0 < np.abs(feats["bf16"] - feats["fp32"]).max() < 0.1 * scale  # autocast acted (an untrained net: ~6 %)
    maps = {p: late_outputs(model, feats["fp32"], precision=p) for p in ("fp32", "bf16")}
    assert maps["bf16"][0].dtype == np.float32 and np.abs(maps["bf16"][0] - maps["fp32"][0]).max() < 0.05
    inp = FusionInputs(senders=["a", "b"], rel_poses=np.array([[0, 0, 0], [5, 0, 0.1]], np.float32))
    inp.features = {"a": feats["fp32"], "b": feats["fp32"]}
    preds = {p: predict("cobevt", model, inp, 64, p) for p in ("fp32", "bf16")}
    for k, v in preds["bf16"].probs.items():
        assert v.dtype == np.float32 and 0 < np.abs(v - preds["fp32"].probs[k]).max() < 0.05, k

"""perception.fusion_threads: several methods fused at once give every method the very prediction it gives
alone, and the setting resolves as documented."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.build import build_cooperative
from tests.v2vsim.perception._clouds import cloud
from v2vsim.config import ConfigError, load_scenario
from v2vsim.evaluation.fuse_and_score import predict_all
from v2vsim.perception.encode import encode_points, late_outputs
from v2vsim.perception.fuse import FusionInputs
from v2vsim.perception.precision import native_bf16
from v2vsim.perception.threads import fusion_pool, fusion_threads


def test_auto_is_one_thread_per_core_at_most_one_per_method() -> None:
    assert fusion_threads(0, methods=8, cpus=2) == 2
    assert fusion_threads(0, methods=1, cpus=16) == 1
    assert fusion_threads(0, methods=8, cpus=1) == 1
    assert fusion_threads(3, methods=8, cpus=1) == 3  # asked for: as many as asked, not more than methods
    assert fusion_threads(12, methods=2, cpus=64) == 2
    assert fusion_pool(1) is None
    with pytest.raises(ConfigError, match="perception.fusion_threads"):
        load_scenario("scenarios/intersection.yaml", ["perception.fusion_threads=-1"])


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_methods_fused_side_by_side_are_bit_identical_to_one_at_a_time(precision: str) -> None:
    torch.set_num_threads(1)  # as in every agent process
    methods: tuple[str, ...] = ("none", "late", "early", "fcooper", "v2vnet", "cobevt")
    if precision == "bf16" and not native_bf16():
        # emulated bfloat16 (an AVX2-only CPU) ran V2VNet's three predictions ~75 % of this test's 96 s; it runs
        # it side by side in the float32 case, and in bfloat16 wherever the CPU computes bfloat16 natively
        methods = tuple(m for m in methods if m != "v2vnet")
    models = {}
    for i, m in enumerate(methods):
        torch.manual_seed(i)
        models[m] = build_cooperative("pointpillars", m, "tiny").eval()
    enc = models["none"].encoder
    for m in methods:
        if m != "early":
            models[m].encoder = enc
    senders = ["a", "b", "c"]
    inp = FusionInputs(senders=senders, rel_poses=np.array([[0, 0, 0], [6, -2, 0.1], [-9, 4, -0.3]], np.float32))
    clouds = {s: cloud(i, n=4000) for i, s in enumerate(senders)}
    inp.points = clouds
    inp.features = {s: encode_points(enc, clouds[s], precision) for s in senders}
    inp.outputs = {s: late_outputs(models["late"], inp.features[s], precision=precision) for s in senders}
    serial = predict_all(models, inp, 64, precision)
    with fusion_pool(3) as pool:  # type: ignore[union-attr]
        for _ in range(2):
            # the longest first (cost), or in models' order: the same predictions, returned in models' order
            side = predict_all(models, inp, 64, precision, pool=pool, cost={"cobevt": 9.0, "early": 5.0} if _ else None)
            assert list(side) == list(serial) == list(methods)
            for m in methods:
                for k, v in serial[m].probs.items():
                    assert np.array_equal(v, side[m].probs[k]), (m, k)
                a, b = serial[m].boxes, side[m].boxes
                assert (a is None and b is None) or np.array_equal(a, b), m

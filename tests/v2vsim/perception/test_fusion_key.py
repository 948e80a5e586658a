"""fusion_key: the digest of exactly what predict() reads, by which replays of one recording in one process share
predictions. Equal keys must mean equal predictions; a change predict sees must change the key."""

from __future__ import annotations

import numpy as np
import torch

from models.build import build_cooperative
from v2vsim.perception.fuse import FusionInputs, fusion_key, predict

METHODS = ("none", "late", "early", "fcooper", "cobevt")


def _inputs(rng: np.random.Generator, c: int, f: int) -> FusionInputs:
    senders = ["a", "b", "c"]
    rel = rng.normal(size=(3, 3)).astype(np.float32)
    rel[0] = 0
    inp = FusionInputs(senders=senders, rel_poses=rel, poses_by_kind={k: rel.copy() for k in
                                                                      ("features", "points", "outputs")})
    for s in senders:
        inp.features[s] = rng.normal(size=(c, f, f)).astype(np.float32)
        inp.points[s] = rng.uniform(-20, 20, size=(300, 4)).astype(np.float32)
        inp.outputs[s] = (rng.uniform(size=(3, 32, 32)).astype(np.float32), np.zeros((0, 6), np.float32))
    return inp


def _variant(inp: FusionInputs, what: str) -> FusionInputs:
    out = FusionInputs(senders=list(inp.senders), rel_poses=inp.rel_poses.copy(),
                       poses_by_kind={k: v.copy() for k, v in inp.poses_by_kind.items()},
                       features=dict(inp.features), points=dict(inp.points), outputs=dict(inp.outputs))
    if what == "neighbour features":
        out.features["b"] = inp.features["b"] + 1
    elif what == "ego features":
        out.features["a"] = inp.features["a"] + 1
    elif what == "neighbour points":
        out.points["c"] = inp.points["c"][:200]
    elif what == "neighbour outputs":
        out.outputs["b"] = (inp.outputs["b"][0] * 0.5, inp.outputs["b"][1])
    elif what == "feature poses":
        out.poses_by_kind["features"][1, 0] += 1.0
    elif what == "point poses":
        out.poses_by_kind["points"][2, 1] += 1.0
    elif what == "a neighbour dropped":
        del out.features["c"], out.points["c"], out.outputs["c"]
    return out


# what each method reads (predict): the key must change exactly for these
READS = {
    "none": {"ego features"},
    "late": {"neighbour outputs", "a neighbour dropped"},
    "early": {"neighbour points", "point poses", "a neighbour dropped"},
    "fcooper": {"neighbour features", "ego features", "feature poses", "a neighbour dropped"},
    "cobevt": {"neighbour features", "ego features", "feature poses", "a neighbour dropped"},
}
CHANGES = ("neighbour features", "ego features", "neighbour points", "neighbour outputs", "feature poses",
           "point poses", "a neighbour dropped")


def test_the_key_changes_exactly_with_what_the_method_reads_and_equal_keys_predict_alike() -> None:
    torch.manual_seed(0)
    models = {m: build_cooperative("pointpillars", m, "tiny").eval() for m in METHODS}
    c, f = models["cobevt"].encoder.out_channels, models["cobevt"].encoder.out_cells
    base = _inputs(np.random.default_rng(1), c, f)
    for m, model in models.items():
        k0 = fusion_key(m, base)
        assert fusion_key(m, _variant(base, "")) == k0  # copies of the same inputs: the same key
        for what in CHANGES:
            changed = fusion_key(m, _variant(base, what)) != k0
            assert changed == (what in READS[m]), (m, what)
        p0, p1 = predict(m, model, base, 64), predict(m, model, _variant(base, "neighbour points" if m != "early"
                                                                         else "neighbour outputs"), 64)
        assert p0 is not None and p1 is not None
        for name in p0.probs:  # a change it does not read: the same prediction, bit for bit
            assert np.array_equal(p0.probs[name], p1.probs[name]), (m, name)
    gone = _variant(base, "")
    del gone.features["a"], gone.points["a"], gone.outputs["a"]
    assert all(fusion_key(m, gone).endswith(b"-") for m in METHODS)  # no ego input: predict returns None
    assert fusion_key("cobevt", base) != fusion_key("fcooper", base)  # the method is part of the key

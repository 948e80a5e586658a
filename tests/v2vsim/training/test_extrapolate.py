"""The `extrapolate` stage: FeatureExtrapolation trained on top of the zoo's CoBEVT (frozen) on the feature
cache; exported as an add-on that leaves the zoo's methods as they were; `build_extrapolation` loads it (and
only it: never a random one). Nothing here trains for real."""

from __future__ import annotations

import io
import json
import shutil

import pytest
import torch

from models import zoo
from v2vsim.config import ConfigError, load_scenario
from v2vsim.data.torch_dataset import CooperativeDataset, collate
from v2vsim.perception.build import build_agent_encoder, build_extrapolation, build_method_models
from v2vsim.perception.plan import plan_models
from v2vsim.training.extrapolate import late_messages
from v2vsim.training.stages import SPECS, TrainArgs, stages_for
from v2vsim.training.train import run_stage


def _args(data, tmp_path, stage: str, work: str = "work", **over) -> TrainArgs:
    return TrainArgs(data=data, stage=stage, out=tmp_path / "zoo", work=tmp_path / work, threads=1,
                     overrides=tuple({"epochs": 1, "samples_per_epoch": 2, "batch": 2, "val_samples": 2,
                                      **over}.items()))


def _scenario(tmp_path, *more: str):
    return load_scenario("scenarios/intersection.yaml", [f"perception.weights={tmp_path / 'zoo'}", *more])


def test_the_stage_is_its_own_and_not_part_of_all() -> None:
    assert stages_for("extrapolate") == ["extrapolate"]
    assert "extrapolate" not in stages_for("all") and "extrapolate" not in stages_for("all", "sinbevt")
    spec = SPECS["extrapolate"]
    assert spec.methods == ("cobevt",) and spec.inputs == "cache" and spec.target == "coop"
    assert spec.delays == (1, 2, 3, 4, 5)


def test_late_messages_and_their_steps(tiny_dataset) -> None:
    ds = CooperativeDataset(tiny_dataset, "train", delays=(2,), with_points=False, with_previous=True)
    samples = [ds[i] for i in range(len(ds))]
    batch = collate(samples)
    late = late_messages(batch)
    assert late
    for i, j, p, steps in late:
        s = samples[i]
        assert j > 0 and p == s["agent_frames"][j] - 1 and steps == s["key"].frame - s["agent_frames"][j] == 2
    # frame 2 with delay 2: neighbours from frame 0, which has no message before it -> not extrapolated
    assert not any(samples[i]["key"].frame < 3 for i, *_ in late)


def test_extrapolate_stage_trains_only_the_addon_and_exports_it(tiny_dataset, tmp_path) -> None:
    log = io.StringIO()
    for stage in ("single", "cache", "cobevt"):
        run_stage(_args(tiny_dataset, tmp_path, stage), log=log)
    # before the stage: the zoo has no extrapolation, and none is made up
    assert build_extrapolation(plan_models(_scenario(tmp_path))) is None
    cobevt_before = (tmp_path / "zoo" / "pointpillars_tiny" / "cobevt.pt").read_bytes()

    # the cache for an existing zoo: a --work without single/final.pt encodes with the zoo's encoder
    run_stage(_args(tiny_dataset, tmp_path, "cache", work="work2"), log=log)
    assert "encoding with the zoo's encoder" in log.getvalue()
    src = json.loads((tmp_path / "work2" / "cache" / "encoder.json").read_text())
    assert src["source"].endswith("single.pt")
    assert src["fingerprint"] == json.loads((tmp_path / "work" / "cache" / "encoder.json").read_text())["fingerprint"]
    f1 = (tmp_path / "work" / "cache" / "features.f16").read_bytes()
    assert (tmp_path / "work2" / "cache" / "features.f16").read_bytes() == f1

    # 2 optimisation steps (4 samples each), neighbours 1 frame late so that half the samples have a late message
    args = _args(tiny_dataset, tmp_path, "extrapolate", work="work2", samples_per_epoch=8, batch=4, delays=(1,))
    metrics = run_stage(args, log=log)
    text = log.getvalue()
    assert "without extrapolation" in text and "with it" in text
    assert set(metrics) == {"cobevt", "cobevt_extrapolated"}
    last = torch.load(tmp_path / "work2" / "extrapolate" / "last.pt", weights_only=False)["model"]
    zoo_cobevt = torch.load(tmp_path / "zoo" / "pointpillars_tiny" / "cobevt.pt", weights_only=True)["state_dict"]
    for k, v in zoo_cobevt.items():  # fusion and heads: exactly the zoo's, untouched by the 2 steps
        assert torch.equal(last[k], v), k
    assert (tmp_path / "zoo" / "pointpillars_tiny" / "cobevt.pt").read_bytes() == cobevt_before
    assert torch.count_nonzero(last["extrapolation.net.4.weight"]) > 0  # zero-initialised, then trained

    entry = zoo.read_manifest(tmp_path / "zoo")["zoos"]["pointpillars_tiny"]
    assert entry["methods"] == {"cobevt": "cobevt.pt"} and entry["encoder"] == "single.pt"
    assert entry["extrapolation"] == {"cobevt": "cobevt_extrapolate.pt"}
    info = entry["files"]["cobevt_extrapolate.pt"]
    assert info["stage"] == "extrapolate" and info["command"].startswith("v2vsim train")
    assert info["extrapolates"] == {"method": "cobevt", "file": "cobevt.pt",
                                    "sha256": entry["files"]["cobevt.pt"]["sha256"]}
    assert set(info["validation"]) == {"cobevt", "cobevt_extrapolated"}

    # the ego's build: the trained add-on, verified; the methods load as before
    sc = _scenario(tmp_path)
    plan = plan_models(sc)
    ext = build_extrapolation(plan)
    assert ext is not None and not ext.training
    saved = torch.load(tmp_path / "zoo" / "pointpillars_tiny" / "cobevt_extrapolate.pt", weights_only=True)
    assert saved["stage"] == "extrapolate" and set(saved["state_dict"]) == {
        f"extrapolation.{k}" for k in ext.state_dict()}
    assert all(torch.equal(ext.state_dict()[k[len("extrapolation."):]], v) for k, v in saved["state_dict"].items())
    assert build_extrapolation(plan, "v2vnet") is None
    random = load_scenario("scenarios/intersection.yaml", ["perception.weights=none"])
    assert build_extrapolation(plan_models(random)) is None
    models = build_method_models(plan, build_agent_encoder(plan), ("cobevt",))
    assert all(torch.equal(models["cobevt"].fusion.state_dict()[k[len("fusion."):]], v)
               for k, v in zoo_cobevt.items() if k.startswith("fusion."))

    # a cache made by another encoder than the zoo's is refused
    enc = tmp_path / "work2" / "cache" / "encoder.json"
    enc.write_text(json.dumps({"source": "elsewhere", "fingerprint": "0" * 64}))
    with pytest.raises(ValueError, match="not by the encoder of the zoo"):
        run_stage(args, log=io.StringIO())

    # an add-on trained on another cobevt.pt than the zoo's current one is refused, naming the file
    doc = zoo.read_manifest(tmp_path / "zoo")
    doc["zoos"]["pointpillars_tiny"]["files"]["cobevt_extrapolate.pt"]["extrapolates"]["sha256"] = "f" * 64
    zoo.write_manifest(doc, tmp_path / "zoo")
    with pytest.raises(ConfigError, match="cobevt_extrapolate.pt: trained on top of cobevt.pt"):
        build_extrapolation(plan_models(sc))  # a fresh plan: the manifest changed


def test_build_extrapolation_is_none_for_a_zoo_without_one(tmp_path) -> None:
    root = tmp_path / "zoo"
    root.mkdir()
    doc = zoo.read_manifest()  # the shipped zoo's manifest, less any extrapolation add-on
    for entry in doc["zoos"].values():
        entry.pop("extrapolation", None)
    zoo.write_manifest(doc, root)
    assert build_extrapolation(plan_models(_scenario(tmp_path))) is None


def test_the_stage_needs_the_method_in_the_zoo(tiny_dataset, tmp_path) -> None:
    shutil.rmtree(tmp_path / "zoo", ignore_errors=True)
    from v2vsim.data.layout import DatasetError

    with pytest.raises(DatasetError, match="no cobevt checkpoint"):
        run_stage(_args(tiny_dataset, tmp_path, "extrapolate"), log=io.StringIO())

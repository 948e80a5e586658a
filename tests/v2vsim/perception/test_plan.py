"""The scenario's models resolved once (v2vsim.perception.plan): a run start reads the zoo's manifest once and
verifies each checkpoint file once, without building its models for real; the plan is immutable and holds the
manifest's checkpoints; the check refuses a checkpoint that does not fit, in the words loading it would give."""

from __future__ import annotations

import dataclasses
from collections import Counter

import pytest
import torch

from models import zoo
from tests.models.test_zoo import _broken_zoo
from v2vsim.config import ConfigError, load_scenario
from v2vsim.perception.build import (
    build_agent_encoder,
    build_compressor,
    build_method_models,
    method_checkpoints,
)
from v2vsim.perception.checks import check_scenario
from v2vsim.perception.plan import ModelPlan, plan_models

SCENARIO = "scenarios/intersection.yaml"


@pytest.fixture
def reads(monkeypatch) -> Counter:
    """Reads of each zoo manifest (by folder) and loads (read + sha256) of each checkpoint file (by path)."""
    counts: Counter = Counter()
    read, load = zoo.read_manifest, zoo.Checkpoint.load

    def counting_read(root=zoo.WEIGHTS_DIR):
        counts[("manifest", root)] += 1
        return read(root)

    def counting_load(self):
        counts[("file", self.path)] += 1
        return load(self)

    monkeypatch.setattr(zoo, "read_manifest", counting_read)
    monkeypatch.setattr(zoo.Checkpoint, "load", counting_load)
    return counts


def test_a_run_start_reads_the_manifest_once_and_each_checkpoint_once(reads: Counter) -> None:
    sc = load_scenario(SCENARIO)
    assert not reads
    plan = check_scenario(sc)  # what the runner does at start: the plan, checked, then its notes from the plan
    method_checkpoints(plan, plan.methods)
    assert reads[("manifest", zoo.WEIGHTS_DIR)] == 1 and sum(n for (k, _), n in reads.items() if k == "manifest") == 1
    files = {p: n for (k, p), n in reads.items() if k == "file"}
    assert set(files.values()) == {1}  # each distinct file verified once
    expected = {c.path for c in plan.checkpoints.values() if c is not None} | {plan.compressor.path}
    assert set(files) >= expected
    # a process's models all come from its one plan: no further manifest read
    reads.clear()
    enc = build_agent_encoder(plan)
    build_compressor(plan, enc.out_channels)
    build_method_models(plan, enc, ("none", "cobevt"))
    assert not any(k == "manifest" for k, _ in reads)


def test_the_plan_is_immutable_and_holds_the_manifest_s_checkpoints() -> None:
    sc = load_scenario(SCENARIO)
    plan = plan_models(sc)
    assert isinstance(plan, ModelPlan)
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.wire_ratio = 1  # type: ignore[misc]
    with pytest.raises(TypeError):
        plan.checkpoints["cobevt"] = None  # type: ignore[index]
    entry = zoo.zoo_entry("pointpillars", "tiny")
    folder = zoo.WEIGHTS_DIR / "pointpillars_tiny"
    assert plan.zoo is not None and plan.wire_ratio == entry["wire_ratio"] and plan.cells == entry["cells"]
    assert plan.methods == tuple(sc.perception.methods)
    assert plan.checkpoints["encoder"].path == folder / entry["encoder"]
    for m in sc.perception.methods:
        ckpt = plan.checkpoint(m)
        name = entry["methods"][m]
        assert ckpt.path == folder / name and ckpt.sha256 == entry["files"][name]["sha256"], m
    ratio = str(plan.wire_ratio)
    assert plan.compressor.sha256 == entry["files"][entry["compressors"][ratio]]["sha256"]
    assert {m: c.path.name for m, c in plan.extrapolation.items()} == entry.get("extrapolation", {})
    random = plan_models(load_scenario(SCENARIO, ["perception.weights=none"]))
    assert random.zoo is None and random.wire_ratio == 1 and set(random.checkpoints.values()) == {None}
    with pytest.raises(ValueError, match="not part of this model plan"):
        plan.checkpoint("maxmix")


def test_what_a_zoo_cannot_give_is_raised_where_it_is_needed() -> None:
    """A ratio without a trained compressor: planning succeeds (a process that sends no features never needs
    it); building or checking the compressor raises the error naming the ratio."""
    sc = load_scenario(SCENARIO, ["comm.channel_compression=2"])
    plan = plan_models(sc)
    with pytest.raises(ConfigError, match="no trained compressor for ratio 2"):
        build_compressor(plan, 64)
    with pytest.raises(ConfigError, match="no trained compressor for ratio 2"):
        check_scenario(sc)


def test_a_checkpoint_with_a_resized_weight_is_refused_by_the_check(tmp_path) -> None:
    root, target = _broken_zoo(tmp_path, "none")
    ckpt = torch.load(target, map_location="cpu", weights_only=True)
    key = next(k for k, v in ckpt["state_dict"].items() if k.startswith("fusion.") and v.dim() >= 2)
    w = ckpt["state_dict"][key]
    ckpt["state_dict"][key] = torch.zeros(w.shape[0] + 1, *w.shape[1:], dtype=w.dtype)
    torch.save(ckpt, target)
    doc = zoo.read_manifest(root)
    doc["zoos"]["pointpillars_tiny"]["files"]["cobevt.pt"]["sha256"] = zoo.sha256(target)
    zoo.write_manifest(doc, root)
    sc = load_scenario(SCENARIO, [f"perception.weights={root}"])
    with pytest.raises(ConfigError, match=r"cobevt checkpoint's fusion weights do not fit this version of the model "
                                          r".*size mismatch for .*--stage cobevt") as checked:
        check_scenario(sc)
    plan = plan_models(sc)
    with pytest.raises(ConfigError) as loaded:  # loading it for real says the same
        build_method_models(plan, build_agent_encoder(plan), ("cobevt",))
    assert str(checked.value) == str(loaded.value)
    assert str(target) in str(checked.value) and "\n" not in str(checked.value)

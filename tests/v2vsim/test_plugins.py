"""Fusion plugins (models.registry) through the harness: the scenario's perception.methods and --methods accept them,
`v2vsim run / sweep / train / models` refuse a broken one in one line with exit code 2 (`models` lists it as broken),
`v2vsim train --stage NAME` has a stage for each, and a plugin's checkpoint comes from the scenario's zoo or from the
zoo it ships, only if trained on that zoo's encoder and wire."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch

from models import zoo
from models.registry import BUILTIN_METHODS, fusion_kwargs
from v2vsim.cli import main
from v2vsim.config import ConfigError, PerceptionConfig, check_plugins, load_scenario
from v2vsim.perception.build import build_agent_encoder, build_method_models, method_checkpoints
from v2vsim.perception.plan import plan_models
from v2vsim.training.stages import PLUGIN_SPEC, SPECS, stage_spec, stages_for

SCENARIO = "scenarios/intersection.yaml"

PLUGINS = '''
import torch
from torch import nn

WEIGHTS = None


class MaxMix(nn.Module):
    weights = WEIGHTS

    def __init__(self, channels):
        super().__init__()
        self.mix = nn.Conv2d(channels, channels, 1)

    def forward(self, features, valid_mask):
        neg = torch.full((), float("-inf"), dtype=features.dtype)
        return self.mix(torch.where(valid_mask[:, :, None, None, None], features, neg).amax(dim=1))


class WrongShape(nn.Module):
    def __init__(self, channels):
        super().__init__()

    def forward(self, features, valid_mask):
        return features[:, 0, :4]
'''


@pytest.fixture
def plugins(fake_site):
    fake_site.install("someplug", "someplug_mod", PLUGINS, {"maxmix": "someplug_mod:MaxMix",
                                                            "wrongshape": "someplug_mod:WrongShape"})
    return fake_site


def _one_error_line(err: str, *parts: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("v2vsim: error: "), err
    for p in parts:
        assert p in lines[0], (p, lines[0])


def test_scenarios_name_plugins(plugins) -> None:
    sc = load_scenario(SCENARIO, ["perception.methods=[none, maxmix]"])
    assert sc.perception.methods == ("none", "maxmix")
    check_plugins(sc)
    assert PerceptionConfig().methods == BUILTIN_METHODS  # the default: the built-ins; a plugin runs when named
    with pytest.raises(ConfigError, match=r"perception.methods: got \['none', 'maxmiks'\]; allowed: a non-empty "
                                          r"list of none, late, .*, cobevt, maxmix, wrongshape"):
        load_scenario(SCENARIO, ["perception.methods=[none, maxmiks]"])
    broken = load_scenario(SCENARIO, ["perception.methods=[none, wrongshape]"])  # a name is all the schema checks
    with pytest.raises(ConfigError, match=r"intersection.yaml: perception.methods: fusion method 'wrongshape' "
                                          r"\(entry point wrongshape = someplug_mod:WrongShape in group "
                                          r"v2vsim.fusion of distribution someplug 0.1\): forward\(.*\) returned"):
        check_plugins(broken)


def test_every_verb_refuses_a_broken_plugin_in_one_line(plugins, tmp_path: Path, capsys) -> None:
    what = ("'wrongshape'", "entry point wrongshape = someplug_mod:WrongShape", "someplug 0.1",
            "expected a float32 tensor [B, C, H, W]")
    assert main(["run", SCENARIO, "--methods", "none,wrongshape", "--frames", "1", "--out", str(tmp_path / "run"),
                 "--set", "output.rerun=false"]) == 2
    _one_error_line(capsys.readouterr().err, "perception.methods", *what)
    assert not (tmp_path / "run" / "metrics.json").exists()
    assert main(["sweep", SCENARIO, "--seeds", "0", "--methods", "none,wrongshape", "--frames", "1", "--out",
                 str(tmp_path / "sweep")]) == 2
    _one_error_line(capsys.readouterr().err, "perception.methods", *what)
    assert main(["train", "--data", str(tmp_path / "data"), "--stage", "wrongshape", "--out", str(tmp_path / "zoo"),
                 "--work", str(tmp_path / "work")]) == 2
    _one_error_line(capsys.readouterr().err, *what)
    assert main(["models", "--json"]) == 2  # listed, with the reason, beside the plugin that works
    out = capsys.readouterr()
    rows = {r["name"]: r for r in json.loads(out.out)}
    assert rows["maxmix"]["origin"] == "plugin someplug 0.1" and rows["maxmix"]["output"] == [1, 64, 64, 64]
    assert rows["cobevt"]["origin"] == "built-in" and "error" not in rows["cobevt"]
    assert all(p in rows["wrongshape"]["error"] for p in what) and rows["wrongshape"]["params"] is None
    _one_error_line(out.err, "1 fusion plugin(s) cannot be used: wrongshape")


def test_a_plugin_is_a_training_stage_like_attfuse(plugins) -> None:
    spec = stage_spec("maxmix")
    assert spec == dataclasses.replace(SPECS["attfuse"], name="maxmix", methods=("maxmix",))
    assert PLUGIN_SPEC.inputs == "cache" and PLUGIN_SPEC.target == "coop"  # fusion + heads on the frozen features
    assert stages_for("maxmix") == ["maxmix"] and "maxmix" not in stages_for("all")
    with pytest.raises(ValueError, match="or a fusion plugin's name: maxmix, wrongshape"):
        stages_for("maxmiks")


def _plugin_zoo(folder: Path, manifest: Path) -> Path:
    """A zoo as a plugin ships it: the manifest `v2vsim train --out` wrote (copied from the installed zoo: it records
    the encoder and wire compressor the method was trained on) and the method's own checkpoint, nothing else."""
    folder.mkdir()
    shutil.copy(manifest, folder / zoo.MANIFEST)
    torch.manual_seed(5)
    mix = torch.nn.Conv2d(64, 64, 1)
    path = folder / "pointpillars_tiny" / "maxmix.pt"
    zoo.save_checkpoint(path, {f"fusion.mix.{k}": v for k, v in mix.state_dict().items()}, encoder="pointpillars",
                        preset="tiny", stage="maxmix", methods=["maxmix"], config={})
    zoo.register(path, encoder="pointpillars", preset="tiny", methods=["maxmix"], info={"stage": "maxmix"},
                 root=folder)
    return path


def test_a_plugin_brings_its_own_weights_for_the_installed_zoo(fake_site, tmp_path: Path) -> None:
    shipped = _plugin_zoo(tmp_path / "weights", zoo.WEIGHTS_DIR / zoo.MANIFEST)
    fake_site.install("weightplug", "weightplug_mod", PLUGINS.replace("WEIGHTS = None",
                                                                      f"WEIGHTS = {str(tmp_path / 'weights')!r}"),
                      {"maxmix": "weightplug_mod:MaxMix"})
    sc = load_scenario(SCENARIO, ["perception.methods=[none, maxmix]"])  # perception.weights: auto
    plan = plan_models(sc)
    checkpoints = method_checkpoints(plan, ("none", "maxmix"))
    assert checkpoints == {"none": "pointpillars_tiny/none.pt", "maxmix": str(shipped)}
    model = build_method_models(plan, build_agent_encoder(plan), ("maxmix",))["maxmix"]
    saved = torch.load(shipped, weights_only=True)["state_dict"]
    assert torch.equal(model.fusion.mix.weight, saved["fusion.mix.weight"])

    # trained on another encoder than the installed zoo's: refused, never run on features it never saw
    doc = json.loads((tmp_path / "weights" / zoo.MANIFEST).read_text())
    doc["zoos"]["pointpillars_tiny"]["files"]["single.pt"]["sha256"] = "0" * 64
    (tmp_path / "weights" / zoo.MANIFEST).write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match="fusion plugin 'maxmix': the checkpoint it ships .* was trained on another "
                                          "model than the pointpillars_tiny zoo .*its encoder"):
        method_checkpoints(plan_models(sc), ("maxmix",))  # a fresh plan: the manifest changed


def test_a_plugin_without_weights_runs_untrained_and_says_so(plugins) -> None:
    sc = load_scenario(SCENARIO, ["perception.methods=[none, maxmix]"])
    plan = plan_models(sc)
    assert method_checkpoints(plan, ("none", "maxmix")) == {"none": "pointpillars_tiny/none.pt", "maxmix": None}
    assert fusion_kwargs("maxmix", "paper") == {}

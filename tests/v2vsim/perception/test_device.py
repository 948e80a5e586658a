"""perception.device: resolved on the host that infers (auto -> the CPU without CUDA), a CUDA device this host lacks
named in one ConfigError, and models moved to the CPU computing exactly what they computed before."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from models.build import build_cooperative
from models.compression import ChannelCompressor
from tests.v2vsim.perception._clouds import cloud
from v2vsim.config import ConfigError, load_scenario
from v2vsim.perception import device as D
from v2vsim.perception.build import compress, decompress
from v2vsim.perception.checks import check_scenario
from v2vsim.perception.encode import encode_points, late_outputs
from v2vsim.perception.fuse import FusionInputs, predict

needs_no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="checks a host without CUDA")


@needs_no_cuda
def test_on_a_host_without_cuda_auto_and_cpu_are_the_cpu_and_cuda_is_refused_naming_the_key() -> None:
    assert D.resolve_device("auto") == torch.device("cpu") and D.resolve_device("cpu") == torch.device("cpu")
    for asked in ("cuda", "cuda:0", "cuda:3"):
        with pytest.raises(ConfigError) as e:
            D.resolve_device(asked)
        msg = str(e.value)
        assert msg.startswith(f"perception.device: {asked!r} asked") and "no CUDA device" in msg and "\n" not in msg
    with pytest.raises(ConfigError, match="perception.device: 'gpu'"):
        D.resolve_device("gpu")


def test_cuda_out_of_range_names_what_the_host_has(monkeypatch: pytest.MonkeyPatch) -> None:
    # a pretend host with one GPU: the index check, without a GPU
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    assert D.resolve_device("auto") == torch.device("cuda", 0) and D.resolve_device("cuda") == torch.device("cuda", 0)
    assert D.resolve_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(ConfigError, match=r"perception.device: 'cuda:1' asked, but this host has 1 CUDA device "
                                          r"\(cuda:0..cuda:0\)"):
        D.resolve_device("cuda:1")


def test_the_schema_checks_the_spelling_and_the_runner_checks_the_host() -> None:
    assert load_scenario("scenarios/intersection.yaml").perception.device == "auto"
    with pytest.raises(ConfigError, match="perception.device: got 'gpu'; allowed: auto, cpu, cuda or cuda:N"):
        load_scenario("scenarios/intersection.yaml", ["perception.device=gpu"])
    if not torch.cuda.is_available():
        sc = load_scenario("scenarios/intersection.yaml", ["perception.device=cuda"])
        with pytest.raises(ConfigError, match=r"intersection.yaml: perception.device: 'cuda' asked"):
            check_scenario(sc)


@needs_no_cuda
def test_the_record_and_the_report_line_say_auto_fell_back_to_the_cpu() -> None:
    rec = D.device_record("auto", D.resolve_device("auto"))
    assert rec["asked"] == "auto" and rec["used"] == "cpu" and rec["name"]
    assert "auto ran on the CPU" in D.device_line(rec)
    assert "auto ran" not in D.device_line(D.device_record("cpu", torch.device("cpu")))
    assert D.device_record("cpu", torch.device("cpu"))["name"] == D.cpu_name()


def test_model_device_and_prepare_leave_the_cpu_as_it_was() -> None:
    assert D.model_device(torch.nn.ReLU()) == torch.device("cpu")
    assert D.model_device(torch.nn.Linear(2, 2)) == torch.device("cpu")
    flags = (torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic,
             torch.are_deterministic_algorithms_enabled())
    D.prepare(torch.device("cpu"))  # the CPU path sets nothing process-wide
    assert flags == (torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic,
                     torch.are_deterministic_algorithms_enabled())


def test_models_moved_to_the_cpu_device_compute_bit_for_bit_what_they_did() -> None:
    torch.manual_seed(0)
    before = build_cooperative("pointpillars", "cobevt", "tiny").eval()
    moved = copy.deepcopy(before).to(D.resolve_device("cpu"))  # as the agents do
    comp = ChannelCompressor(64, 8).eval()
    comp_moved = copy.deepcopy(comp).to(D.resolve_device("cpu"))
    with torch.no_grad():  # the path before perception.device, spelled out: no device, no copies
        today = before.encoder([torch.from_numpy(cloud())])[0].float().numpy()
    feats = encode_points(before.encoder, cloud())
    assert np.array_equal(feats, today) and np.array_equal(encode_points(moved.encoder, cloud()), today)
    for a, b in zip(late_outputs(before, feats), late_outputs(moved, feats), strict=True):
        assert np.array_equal(a, b)
    wire = compress(comp, feats)
    assert np.array_equal(compress(comp_moved, feats), wire)
    assert np.array_equal(decompress(comp_moved, wire.astype(np.float16)), decompress(comp, wire.astype(np.float16)))
    inp = FusionInputs(senders=["a", "b"], rel_poses=np.array([[0, 0, 0], [5, 0, 0.1]], np.float32))
    inp.features = {"a": feats, "b": feats}
    p0, p1 = predict("cobevt", before, inp, 64), predict("cobevt", moved, inp, 64)
    assert p0 is not None and p1 is not None and np.array_equal(p0.boxes, p1.boxes)
    for k, v in p0.probs.items():
        assert np.array_equal(v, p1.probs[k]), k

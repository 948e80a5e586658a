"""The models' half of the GPU check, without SUMO, zenoh or rerun (a GPU host that lacks them): the tiny LiDAR zoo's
encoder, late outputs (heads + box decoding + NMS) and CoBEVT's fusion on `cuda` against the CPU, through the same
functions the agents use (v2vsim.perception.device, .encode, .fuse). Prints the largest differences and the time of
each; exits 1 when a vehicle probability differs by more than --tol.

    python scripts/gpu_models_check.py [--tol 0.01]
"""

from __future__ import annotations

import argparse
import copy
import sys
import time

import numpy as np
import torch

try:  # v2vsim.perception.encode imports the sensing modules (shapely) for a type; this check senses nothing
    import shapely  # noqa: F401
except ModuleNotFoundError:  # a bare GPU host: a stand-in for that module lets the import through, unused here
    import types

    _sensing = types.ModuleType("v2vsim.sensors.sensing")
    _sensing.SensorFrame = object  # type: ignore[attr-defined]
    sys.modules["v2vsim.sensors.sensing"] = _sensing

from models.build import build_cooperative
from v2vsim.perception import device as D
from v2vsim.perception.encode import encode_points, late_outputs
from v2vsim.perception.fuse import FusionInputs, predict


def cloud(n: int = 30000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-50, 50, (n, 2)), rng.uniform(-2, 2, (n, 1)), rng.uniform(0, 1, (n, 1))]
    return pts.astype(np.float32)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--tol", type=float, default=0.01)
    tol = ap.parse_args().tol
    dev = D.resolve_device("auto")
    print(f"torch {torch.__version__}, device {dev} ({D.device_name(dev)})")
    if dev.type != "cuda":
        print("no CUDA device: nothing to compare")
        return 0
    D.prepare(dev)
    torch.manual_seed(0)
    cpu = build_cooperative("pointpillars", "cobevt", "tiny").eval()
    gpu = copy.deepcopy(cpu).to(dev)
    worst = 0.0
    with torch.no_grad():
        for model in (cpu, gpu):
            encode_points(model.encoder, cloud())  # warm-up
        t = {}
        feats = {}
        for name, model in (("cpu", cpu), ("gpu", gpu)):
            t0 = time.perf_counter()
            feats[name] = encode_points(model.encoder, cloud())
            t[name] = (time.perf_counter() - t0) * 1000
        print(f"encoder: max |cpu - gpu| {np.abs(feats['cpu'] - feats['gpu']).max():.2e}; "
              f"{t['cpu']:.1f} ms cpu, {t['gpu']:.1f} ms gpu")
        outs = {n: late_outputs(m, feats["cpu"]) for n, m in (("cpu", cpu), ("gpu", gpu))}
        d = np.abs(outs["cpu"][0] - outs["gpu"][0]).max()
        print(f"late outputs: max |prob diff| {d:.2e}; boxes {len(outs['cpu'][1])} cpu, {len(outs['gpu'][1])} gpu")
        worst = max(worst, float(d))
        inp = FusionInputs(senders=["a", "b"], rel_poses=np.array([[0, 0, 0], [5, 0, 0.1]], np.float32))
        inp.features = {"a": feats["cpu"], "b": feats["cpu"]}
        preds = {}
        for name, model in (("cpu", cpu), ("gpu", gpu)):
            predict("cobevt", model, inp, 256)
            t0 = time.perf_counter()
            preds[name] = predict("cobevt", model, inp, 256)
            t[name] = (time.perf_counter() - t0) * 1000
        d = max(float(np.abs(preds["cpu"].probs[k] - preds["gpu"].probs[k]).max()) for k in preds["cpu"].probs)
        print(f"cobevt predict: max |prob diff| {d:.2e}; {t['cpu']:.1f} ms cpu, {t['gpu']:.1f} ms gpu; boxes "
              f"{len(preds['cpu'].boxes)} cpu, {len(preds['gpu'].boxes)} gpu")
        worst = max(worst, d)
    ok = worst <= tol
    print(f"largest probability difference {worst:.2e}: {'within' if ok else 'BEYOND'} tolerance {tol}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

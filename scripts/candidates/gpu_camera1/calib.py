"""Throughput calibration of the camera `single` stage on a small dataset, through the trainer's own pieces
(build_stage_model with the ImageNet Lite0, param_groups, AdamW, bf16 autocast, forward, perception_loss):
seconds per training step of batch B on the device (one batch reused: the loader is measured apart),
seconds per loaded sample (one process), seconds per validation sample (validate(), torch threads T).
Prints one JSON line prefixed "CALIB ".
    python3 calib.py DATA DEVICE STEPS BATCH VAL_SAMPLES THREADS"""

import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

from v2vsim.data.torch_dataset import CooperativeDataset, collate
from v2vsim.training.losses import perception_loss
from v2vsim.training.stages import SPECS, TrainArgs, build_stage_model, param_groups
from v2vsim.training.train import forward
from v2vsim.training.validate import validate


def main() -> None:
    data, device, steps, batch_n, val_n, threads = (Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]),
                                                    int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6]))
    torch.set_num_threads(threads)
    dev = torch.device(device)
    spec = dataclasses.replace(SPECS["single"], batch=batch_n)
    args = TrainArgs(data=data, stage="single", out=Path("/tmp/unused_zoo"), work=Path("/tmp/unused_work"),
                     encoder="sinbevt", device=device, bf16=True)
    res: dict = {}
    t = time.perf_counter()
    ds = CooperativeDataset(data, "train", max_agents=1, delays=(0,), seed=0, with_points=False, with_images=True)
    val = CooperativeDataset(data, "val", max_agents=5, egos="first", with_points=False, with_images=True, stride=2,
                             delays=(0,), seed=0)
    res["keys_s_per_frame"] = (time.perf_counter() - t) / max(1, len(ds) / 4 + len(val))
    n = min(len(ds), 48)
    t = time.perf_counter()
    items = [ds[i * len(ds) // n] for i in range(n)]
    res["load_s_per_sample"] = (time.perf_counter() - t) / n
    t = time.perf_counter()
    batch = collate(items[:batch_n])
    res["collate_s_per_batch"] = time.perf_counter() - t
    model = build_stage_model(args, spec).to(dev)
    model.train()
    groups = param_groups(model, spec)
    params = [p for g in groups for p in g["params"]]
    opt = torch.optim.AdamW(groups, lr=spec.lr, weight_decay=1e-2)
    assert model.heads.detection is None  # camera: no anchor head (the trainer's assigner is None)

    def step() -> float:
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=True):
            out = forward(model, spec, batch, None, dev)
        out = {k: v.float() for k, v in out.items()}
        losses = perception_loss(out, batch, spec.target, None, spec.lane_weight)
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        torch.nn.utils.clip_grad_norm_(params, 10.0)
        opt.step()
        return float(losses["total"].detach())  # the trainer reads every loss each step (a sync)

    for _ in range(min(3, steps)):
        step()
    if dev.type == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(steps):
        loss = step()
    if dev.type == "cuda":
        torch.cuda.synchronize()
    res["step_s"] = (time.perf_counter() - t) / steps
    res["loss"] = loss
    if dev.type == "cuda":
        res["max_mem_gib"] = torch.cuda.max_memory_allocated() / 2**30
    t = time.perf_counter()
    validate(spec, model, model, val, None, val_n)
    res["val_s_per_sample"] = (time.perf_counter() - t) / min(val_n, len(val))
    res["batch"] = batch_n
    print("CALIB " + json.dumps(res), flush=True)


if __name__ == "__main__":
    main()

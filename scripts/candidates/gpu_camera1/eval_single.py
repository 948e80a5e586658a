"""Score camera `single` checkpoints (zoo single.pt files) on a dataset split through the trainer's own validation
path (v2vsim.training.validate.validate: `none` and `late`, at most 5 agents, egos=first, stride 2), on the CPU.
    python3 eval_single.py DATA SPLIT N_SAMPLES NAME=PATH/single.pt [NAME=PATH ...]"""
import json
import sys
import time
from pathlib import Path

import torch

from models import zoo
from v2vsim.data.torch_dataset import CooperativeDataset
from v2vsim.training.stages import SPECS, TrainArgs, build_training_model
from v2vsim.training.validate import validate

data, split, n = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
torch.set_num_threads(int(__import__("os").environ.get("THREADS", "1")))
spec = SPECS["single"]
ds = CooperativeDataset(data, split, max_agents=5, egos="first", with_points=False, with_images=True, stride=2,
                        delays=(0,), seed=0)
print(f"{data} {split}: {len(ds)} samples, scoring {min(n, len(ds))}", flush=True)
out = {}
for arg in sys.argv[4:]:
    name, path = arg.split("=", 1)
    path = Path(path)
    entry = zoo.zoo_entry("sinbevt", "tiny", path.parent.parent)
    state = zoo.load_checkpoint(path, entry)
    args = TrainArgs(data=data, stage="single", out=path.parent.parent, work=Path("/tmp/unused"), encoder="sinbevt",
                     image_backbone=zoo.zoo_image_backbone(entry))
    model = build_training_model(args, "none")
    missing, unexpected = model.load_state_dict(state, strict=False)
    assert not unexpected and all(k.startswith("fusion.") for k in missing), (missing, unexpected)
    t = time.time()
    m = validate(spec, model, model, ds, None, n)
    out[name] = m
    print(name, f"{time.time() - t:.0f} s", json.dumps({k: {x: v[x] for x in ("iou_vehicle", "iou_road", "iou_lane")}
                                                      for k, v in m.items()}), flush=True)
print(json.dumps(out))

"""The ego side of learned latency compensation (comm.compensation): each late neighbour's features moved to
the fused frame's instant by the zoo's FeatureExtrapolation (models.extrapolation, FFNet's first-order feature
flow), from that sender's two latest messages. Messages fused aligned (age 0) are left as they are."""

from __future__ import annotations

import numpy as np
import torch

from models.extrapolation import FeatureExtrapolation, compensate, extrapolation_steps
from v2vsim.perception.device import model_device, to_host
from v2vsim.perception.fuse import FusionInputs


@torch.no_grad()
def extrapolate_features(module: FeatureExtrapolation, inp: FusionInputs, bev_size_m: float) -> dict[str, np.ndarray]:
    """Sender -> [C, F, F] float32 features extrapolated by their age, for every neighbour with a late message
    and a message before it (inp.previous_features, already decompressed to [C, F, F])."""
    out: dict[str, np.ndarray] = {}
    device = model_device(module)  # on the module's device; each result back on the host
    for s, (old, rel, gap_s) in inp.previous_features.items():
        age = inp.feature_ages.get(s, 0.0)
        steps = extrapolation_steps(age, gap_s)
        if s not in inp.features or steps <= 0:
            continue
        new = torch.from_numpy(np.ascontiguousarray(inp.features[s], dtype=np.float32))[None]  # [1, C, F, F]
        prev = torch.from_numpy(np.ascontiguousarray(old, dtype=np.float32))[None]
        moved = compensate(module, new.to(device), prev.to(device),
                           torch.from_numpy(np.asarray(rel, np.float32))[None].to(device),
                           torch.tensor([steps], dtype=torch.float32, device=device), bev_size_m)
        out[s] = to_host(moved[0])
    return out

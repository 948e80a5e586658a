"""The `extrapolate` stage's inputs: every late message of a batch extrapolated to the ego's frame time from the
message its sender sent before it (models.extrapolation), both read from the feature cache."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from models.compression import ChannelCompressor
from models.extrapolation import FeatureExtrapolation, compensate
from v2vsim.training.cache import FeatureCache


def late_messages(batch: dict) -> list[tuple[int, int, int, float]]:
    """(sample, slot, previous frame, steps) of every agent of a with_previous batch whose message is late and
    has one before it; steps = its age / the time between the two messages, both in frames."""
    out = []
    for i, (key, frames, prevs) in enumerate(zip(batch["key"], batch["agent_frames"], batch["prev_frames"],
                                                 strict=True)):
        for j, (k, p) in enumerate(zip(frames, prevs, strict=True)):
            if p >= 0 and key.frame > k:
                out.append((i, j, p, (key.frame - k) / (k - p)))
    return out


def extrapolate_batch(module: FeatureExtrapolation, feats: Tensor, batch: dict, cache: FeatureCache,
                      bev_size_m: float, wire: ChannelCompressor | None = None) -> Tensor:
    """feats [B, L, C, F, F] (each agent's message, in its own frame) with every late message extrapolated;
    the others (the ego, neighbours without an earlier message) are returned unchanged. The earlier messages
    pass through the `wire` compressor (the zoo's wire ratio) like `feats` did."""
    late = late_messages(batch)
    if not late:
        return feats
    ii = torch.tensor([i for i, _, _, _ in late])
    jj = torch.tensor([j for _, j, _, _ in late])
    old = torch.stack([torch.from_numpy(cache.get(batch["key"][i].run, p, batch["agents"][i][j]).astype(np.float32))
                       for i, j, p, _ in late]).to(feats.device)  # [M, C, F, F]
    if wire is not None:
        with torch.no_grad():
            old = wire.over_the_wire(old)
    steps = torch.tensor([s for _, _, _, s in late], dtype=feats.dtype, device=feats.device)  # [M]
    rel = batch["prev_rel_poses"][ii, jj].to(feats.device)  # [M, 3]: older capture in the newer one's frame
    out = feats.clone()
    out[ii, jj] = compensate(module, feats[ii, jj], old, rel, steps, bev_size_m)
    return out

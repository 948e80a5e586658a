"""Cooperative perception model: per-agent encoder -> warp to ego -> fusion -> decoder + heads.

One module for training and tests; the running simulator splits the same steps across processes
(each CAV calls ``encode`` on its own sensors, the ego calls ``fuse`` + ``heads``).

Methods (models.registry.METHODS):
- intermediate (attfuse, fcooper, v2vnet, disconet, cobevt, and every fusion plugin): every valid agent is
  encoded in its own frame, warped with its relative SE(2) pose (models.warp), fused, decoded once;
- "none": the ego alone; "early": every valid agent's points merged into the ego frame, encoded
  once (LiDAR only); "late": every valid agent runs encoder + heads on its own (training a late
  model = training the single-agent model).

Inference (decoding, late merging, box decoding) has one implementation, used by the ego of a run
and by validation during training alike: ``v2vsim.perception.fuse.predict``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from models.fusion.early import merge_points_to_ego
from models.heads import BevHeads, make_anchors
from models.warp import warp_to_ego

# LiDAR inputs: B x L clouds [P, 4] in each agent's body frame.
# Camera inputs: (images [B, L, M, 3, h, w], intrinsics [B, L, M, 3, 3], extrinsics [B, L, M, 4, 4]).
AgentInputs = Sequence[Sequence[Tensor]] | tuple[Tensor, Tensor, Tensor]


class CooperativePerception(nn.Module):
    """encoder + warp + fusion + heads; forward(inputs, rel_poses [B, L, 3], valid [B, L]) -> outputs."""

    def __init__(
        self,
        encoder: nn.Module,
        fusion: nn.Module,
        heads: BevHeads,
        method: str,
        modality: str,
        bev_size_m: float = 100.0,
    ) -> None:
        super().__init__()
        if modality == "camera" and method == "early":
            raise ValueError("early fusion ships raw LiDAR points; it needs modality 'lidar'")
        self.encoder = encoder
        self.fusion = fusion
        self.heads = heads
        self.method = method
        self.modality = modality
        self.bev_size_m = bev_size_m
        if heads.detection is not None:
            self.register_buffer("anchors", make_anchors(heads.det_cells, bev_size_m), persistent=False)

    # -- the three steps ---------------------------------------------------------------------------

    def encode(self, inputs: AgentInputs, valid: Tensor) -> Tensor:
        """Encode every valid agent in its own frame -> [B, L, C, F, F] (zeros for absent agents)."""
        b, l = valid.shape
        idx = torch.nonzero(valid.cpu())  # [Nv, 2] (batch, slot)
        c, f = self.encoder.out_channels, self.encoder.out_cells
        if self.modality == "lidar":
            clouds = [inputs[int(i)][int(j)] for i, j in idx]
            feats = self.encoder(clouds) if clouds else None
        else:
            images, intr, extr = inputs
            sel = valid.to(images.device)
            feats = self.encoder(images[sel], intr[sel], extr[sel]) if len(idx) else None
        out = torch.zeros(b, l, c, f, f, device=valid.device)
        if feats is not None:
            out = out.index_put((idx[:, 0].to(out.device), idx[:, 1].to(out.device)), feats.to(out.dtype))
        return out

    def fuse(self, features: Tensor, rel_poses: Tensor, valid: Tensor) -> Tensor:
        """Warp sender-frame features [B, L, C, F, F] into the ego frame and fuse -> [B, C, F, F]."""
        warped, _ = warp_to_ego(features, rel_poses, self.bev_size_m)
        return self.fusion(warped, valid)

    def forward(self, inputs: AgentInputs, rel_poses: Tensor, valid: Tensor) -> dict[str, Tensor]:
        """inputs per agent (see AgentInputs), rel_poses [B, L, 3] (dx, dy, dyaw) of each agent in the ego
        body frame (slot 0 = ego = zeros), valid [B, L] bool.

        Returns {"dynamic" [B, 2, S, S], "static" [B, 3, S, S] logits, "det_cls" [B, A, S/2, S/2],
        "det_reg" [B, 6A, S/2, S/2] (LiDAR), "fused" [B, C, F, F]} plus "features" [B, L, C, F, F]
        (intermediate) or per-agent "agent_<key>" [B, L, ...] outputs (late).
        """
        valid = valid.bool()
        if self.method == "none":
            ego = valid.clone()
            ego[:, 1:] = False
            feats = self.encode(inputs, ego)
            fused = feats[:, 0]
            return {"fused": fused, **self.heads(fused)}
        if self.method == "early":
            merged = []
            for i in range(len(inputs)):
                n = len(inputs[i])  # a batch pads rel_poses / valid to its largest agent count
                merged.append([merge_points_to_ego(list(inputs[i]), rel_poses[i, :n].cpu(), valid[i, :n].cpu())])
            fused = self.encode(merged, torch.ones(len(inputs), 1, dtype=torch.bool, device=valid.device))[:, 0]
            return {"fused": fused, **self.heads(fused)}
        feats = self.encode(inputs, valid)  # [B, L, C, F, F]
        if self.method == "late":
            b, l = valid.shape
            per_agent = self.heads(feats.flatten(0, 1))
            out: dict[str, Tensor] = {"fused": feats[:, 0]}
            for k, v in per_agent.items():
                v = v.unflatten(0, (b, l))
                out[f"agent_{k}"] = v
                out[k] = v[:, 0]
            return out
        fused = self.fuse(feats, rel_poses, valid)
        return {"features": feats, "fused": fused, **self.heads(fused)}

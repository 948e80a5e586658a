"""FuseBEVT (CoBEVT supp. Sec. 3.1, Table A2): multi-agent BEV fusion with FAX self-attention.

features [B, L, C, H, W] (ego at slot 0, other agents already warped into the ego frame) ->
``blocks.0..2`` FAX-SA (Eq. 5 local window then Eq. 6 global grid, 3D relative bias over
(agent, row, col)) on the stacked maps -> masked max over present agents -> ``head``:
x + Linear(LayerNorm(x)) -> [B, C, H, W]. This follows the CoBEVT code (max-reduce over agents then
a norm/linear head) rather than reading out slot 0, with the max restricted to present agents.

The head is written in the pre-norm residual form of the FAX-SA blocks, its Linear zero-initialised,
where the CoBEVT code has a plain LayerNorm + Linear. Its fusion is trained from scratch together with
the encoder; here every fusion method fine-tunes heads pretrained on the frozen encoder's raw features
(the zoo recipe), and a randomly initialised projection in front of them undoes that pretraining: the
first batch's loss was 9.7, against 1.0 for none and 1.7 for V2VNet. Residual and zero-initialised, the
head starts as the identity and FuseBEVT near F-Cooper's max (4.2, F-Cooper's own first loss).

Absent agents (``valid_mask`` False) have no influence: their features are replaced by zeros, their
tokens are masked with -inf in every attention's logits and they are excluded from the max, so
changing them changes nothing. When every sample of the batch has the same agents present (e.g. batch
1) the absent slots are dropped instead, which gives the same result faster. The ego slot is always
treated as present. Maps whose sides are not multiples of ``window`` are zero-padded and the padding
is masked the same way, then cropped.

Cost: a window holds L*window^2 tokens, so attention time and memory grow with L^2 (per layer
(H*W/window^2) * heads * (L*window^2)^2 logits; 32x32 maps, 8 agents, window 8: 16.8 M).

Stage submodules (forward-hook names): ``blocks.0..2`` (channels-last [B, L', H, W, C]) and ``head``
([B, C, H, W]); ``FuseBEVT.stage_shapes()`` reports them.

Agent order: the relative bias is indexed by slot offsets n1 - n2, so permuting the non-ego agents
permutes which bias entries pairs of agents use: FuseBEVT is NOT exactly permutation invariant over
non-ego agents (it is when the bias does not depend on the agent offset beyond "same agent or not";
tests check both). The bias table is sized for ``max_agents``; fewer agents use the entries of their
actual slot offsets.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.fax import FAXSelfAttention, trunc_normal_init
from models.resnet import record_stage_shapes

# This method's entry in the registry, read without importing this file (models.registry: METHOD's keys).
# FuseBEVT keeps window = grid = 8 cells on every grid (Table A2's value): on 64 x 64 the local windows are
# 8 x 8 cells (12.5 m, a junction arm and its cars) and the sparse global grid is 8 x 8 cells 8 apart (spanning
# the whole 100 m map), as on 32 x 32 it spans it with cells 4 apart. A 16-cell window would keep the local
# window's 25 m of the 32 x 32 grid at 4x the attention cost (L * 256 tokens per window); the grid study
# (docs/results.md) measured window 8.
METHOD = {"name": "cobevt", "factory": "FuseBEVT", "rank": 8,
          "preset_kwargs": {"paper": {"heads": 4, "window": 8, "blocks": 3, "mlp_dim": 256, "max_agents": 16},
                            "tiny": {"heads": 2, "window": 8, "blocks": 1, "mlp_dim": 128, "max_agents": 16}},
          "paper": {"camera_iou": (60.4, 63.0, 53.0), "lidar_ap70": 0.861}}


class FusionHead(nn.Module):
    """x + Linear(LayerNorm(x)) on the agent-reduced map, channels-last in, [B, C, H, W] out; the Linear
    (``update``) starts at zero, so the head starts as the identity (module docstring)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(channels)
        self.update = nn.Linear(channels, channels)

    def reset_parameters(self) -> None:
        nn.init.zeros_(self.update.weight)
        nn.init.zeros_(self.update.bias)

    def forward(self, x: Tensor) -> Tensor:  # [B, H, W, C] -> [B, C, H, W]
        return (x + self.update(self.norm(x))).permute(0, 3, 1, 2).contiguous()


class FuseBEVT(nn.Module):
    """FuseBEVT: ``blocks`` FAX-SA blocks (window = grid = ``window``) over stacked agent BEV maps."""

    preset_kwargs = METHOD["preset_kwargs"]  # the sizes per preset, where a plugin's class carries them

    def __init__(
        self,
        channels: int,
        heads: int = 4,
        window: int = 8,
        blocks: int = 3,
        mlp_dim: int | None = None,
        max_agents: int = 8,
    ) -> None:
        super().__init__()
        self.channels = channels
        self.window = window
        self.max_agents = max_agents
        mlp = mlp_dim or 2 * channels  # Table A2: dim 128, MLP 256
        self.blocks = nn.ModuleList(
            FAXSelfAttention(channels, heads, window, mlp, max_agents) for _ in range(blocks)
        )
        self.head = FusionHead(channels)
        self.stage_names = tuple(f"blocks.{i}" for i in range(blocks)) + ("head",)
        trunc_normal_init(self)
        self.head.reset_parameters()

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        """features [B, L, C, H, W], valid_mask [B, L] bool (slot 0 = ego) -> fused [B, C, H, W]."""
        b, n, c, h, w = features.shape
        if n > self.max_agents:
            raise ValueError(f"{n} agent slots > max_agents {self.max_agents}")
        valid = valid_mask.to(torch.bool).clone()
        valid[:, 0] = True  # the ego is always present
        p = self.window
        ph, pw = (-h) % p, (-w) % p
        x = features.permute(0, 1, 3, 4, 2)  # [B, L, H, W, C]
        agent_ids: Tensor | None = None
        if bool((valid == valid[:1]).all()):
            # same agents present in every sample: drop the absent slots (exactly equivalent to masking
            # them, and cheaper); relative agent offsets keep using the original slot indices
            ids = valid[0].nonzero().flatten()
            if ids.numel() < n:
                x, agent_ids = x[:, ids], ids
            valid = valid[:, ids]
        x = torch.where(valid[:, :, None, None, None], x, torch.zeros((), dtype=x.dtype, device=x.device))
        inside = torch.ones(h, w, dtype=torch.bool, device=x.device)
        if ph or pw:
            x = F.pad(x, (0, 0, 0, pw, 0, ph))  # pad W then H (channels-last)
            inside = F.pad(inside, (0, pw, 0, ph), value=False)
        token_mask = valid[:, :, None, None] & inside  # [B, L', H', W']
        for blk in self.blocks:
            x = blk(x, token_mask, agent_ids)  # [B, L', H', W', C]
        x = x[:, :, :h, :w]
        x = x.masked_fill(~valid[:, :, None, None, None], float("-inf")).amax(dim=1)  # [B, H, W, C]
        return self.head(x)

    def stage_shapes(self, inputs: tuple[Tensor, Tensor] | None = None) -> list[tuple[str, tuple[int, ...]]]:
        """(stage name, output shape); default inputs: 2 agents on a 32x32 map.

        ``blocks.i`` outputs are channels-last [B, L', H, W, C] (L' = present agents when every sample has
        the same ones, else L); ``head`` is the fused [B, C, H, W].
        """
        if inputs is None:
            inputs = (torch.randn(1, 2, self.channels, 32, 32), torch.ones(1, 2, dtype=torch.bool))
        return record_stage_shapes(self, self.stage_names, lambda: self(*inputs))

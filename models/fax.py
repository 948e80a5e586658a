"""FAX attention (CoBEVT supp. Sec. 2, Eq. 1-6): 3D relative attention, fused block/grid partitions,
the FAX self-attention block (FAX-SA, used by FuseBEVT) and FAX cross-attention (FAX-CA, used by SinBEVT).

Tensor layout is channels-last inside this module: a stack of N agent (or camera) maps is
``[..., N, H, W, C]``. A partition yields ``[..., groups, N*P*P, C]`` whose second-last axis is the
"spatial axis" of Eq. 3/4; tokens inside a group are ordered (n, row, col) with n outermost, so the first
``n*P*P`` tokens of a group are the first n agents.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# --------------------------------------------------------------------------------------------------
# Eq. 3 / Eq. 4: partitions
# --------------------------------------------------------------------------------------------------


def fused_block(x: Tensor, p: int) -> Tensor:
    """Fused-Block (Eq. 3): [..., N, H, W, C] -> [..., (H/P)(W/P), N*P*P, C].

    Group ``a*(W/P) + b`` holds the N x P x P neighbourhood rows [aP, aP+P) x cols [bP, bP+P) of every
    agent; token ``n*P*P + i*P + j`` is agent n at row ``aP+i``, col ``bP+j``.
    """
    *lead, n, h, w, c = x.shape
    if h % p or w % p:
        raise ValueError(f"map {h}x{w} not divisible by window {p}")
    x = x.reshape(*lead, n, h // p, p, w // p, p, c)
    k = len(lead)
    x = x.permute(*range(k), k + 1, k + 3, k, k + 2, k + 4, k + 5)  # [..., H/P, W/P, N, P, P, C]
    return x.reshape(*lead, (h // p) * (w // p), n * p * p, c)


def fused_unblock(x: Tensor, p: int, n: int, h: int, w: int) -> Tensor:
    """Fused-Unblock: inverse of :func:`fused_block`, [..., (H/P)(W/P), N*P*P, C] -> [..., N, H, W, C]."""
    *lead, _, _, c = x.shape
    x = x.reshape(*lead, h // p, w // p, n, p, p, c)
    k = len(lead)
    x = x.permute(*range(k), k + 2, k, k + 3, k + 1, k + 4, k + 5)  # [..., N, H/P, P, W/P, P, C]
    return x.reshape(*lead, n, h, w, c)


def fused_grid(x: Tensor, g: int) -> Tensor:
    """Fused-Grid (Eq. 4): [..., N, H, W, C] -> [..., (H/G)(W/G), N*G*G, C].

    Rows are split as ``G x H/G`` (row = u*(H/G) + s): group ``s*(W/G) + t`` holds the dilated N x G x G
    grid rows {s + u*H/G} x cols {t + v*W/G}; token ``n*G*G + u*G + v`` is agent n at (s + u*H/G, t + v*W/G).
    """
    *lead, n, h, w, c = x.shape
    if h % g or w % g:
        raise ValueError(f"map {h}x{w} not divisible by grid {g}")
    x = x.reshape(*lead, n, g, h // g, g, w // g, c)
    k = len(lead)
    x = x.permute(*range(k), k + 2, k + 4, k, k + 1, k + 3, k + 5)  # [..., H/G, W/G, N, G, G, C]
    return x.reshape(*lead, (h // g) * (w // g), n * g * g, c)


def fused_ungrid(x: Tensor, g: int, n: int, h: int, w: int) -> Tensor:
    """Fused-Ungrid: inverse of :func:`fused_grid`, [..., (H/G)(W/G), N*G*G, C] -> [..., N, H, W, C]."""
    *lead, _, _, c = x.shape
    x = x.reshape(*lead, h // g, w // g, n, g, g, c)
    k = len(lead)
    x = x.permute(*range(k), k + 2, k + 3, k, k + 4, k + 1, k + 5)  # [..., N, G, H/G, G, W/G, C]
    return x.reshape(*lead, n, h, w, c)


def partition(x: Tensor, size: int, mode: str) -> Tensor:
    """``fused_block`` (mode "block", Eq. 3) or ``fused_grid`` (mode "grid", Eq. 4)."""
    return fused_block(x, size) if mode == "block" else fused_grid(x, size)


def unpartition(x: Tensor, size: int, mode: str, n: int, h: int, w: int) -> Tensor:
    """Inverse of :func:`partition`."""
    return fused_unblock(x, size, n, h, w) if mode == "block" else fused_ungrid(x, size, n, h, w)


# --------------------------------------------------------------------------------------------------
# Eq. 2: 3D relative attention
# --------------------------------------------------------------------------------------------------


def relative_position_index(agents: int, window: int) -> Tensor:
    """[T, T] long, T = agents*window^2: table row of the relative (agent, row, col) offset of a token pair.

    Tokens are ordered (n, i, j). For query token (n1, i1, j1) and key token (n2, i2, j2) the entry is
    ``((n1-n2+N-1) * (2P-1) + (i1-i2+P-1)) * (2P-1) + (j1-j2+P-1)`` in [0, (2N-1)(2P-1)^2).
    """
    n, i, j = torch.meshgrid(torch.arange(agents), torch.arange(window), torch.arange(window), indexing="ij")
    coords = torch.stack([n.flatten(), i.flatten(), j.flatten()])  # [3, T]
    rel = coords[:, :, None] - coords[:, None, :]  # [3, T, T]
    span = 2 * window - 1
    rel_n = rel[0] + agents - 1
    rel_i = rel[1] + window - 1
    rel_j = rel[2] + window - 1
    return (rel_n * span + rel_i) * span + rel_j


class Mlp(nn.Module):
    """Channel MLP ``x <- W2 GELU(W1 x)`` (Eq. 5/6; LaRa supp. Eq. 5 with biases)."""

    def __init__(self, dim: int, hidden: int, out_dim: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, out_dim or dim)

    def forward(self, x: Tensor) -> Tensor:  # [..., dim] -> [..., out_dim]
        return self.fc2(F.gelu(self.fc1(x)))


class RelativeAttention3D(nn.Module):
    """Multi-head 3D relative attention (Eq. 2): softmax(QK^T / sqrt(d) + B) V.

    ``B`` comes from ``relative_bias_table`` ([(2N-1)(2P-1)^2, heads], N = ``agents`` = the maximum
    agent count) through the non-persistent buffer ``relative_index`` ([N*P*P, N*P*P]). With n < N
    agents present the first n*P*P tokens are used, i.e. the table is indexed with the actual offsets.
    """

    def __init__(self, dim: int, heads: int, agents: int, window: int) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} not divisible by heads {heads}")
        self.heads = heads
        self.agents = agents
        self.window = window
        self.scale = (dim // heads) ** -0.5
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        table_size = (2 * agents - 1) * (2 * window - 1) ** 2
        self.relative_bias_table = nn.Parameter(torch.zeros(table_size, heads))
        nn.init.trunc_normal_(self.relative_bias_table, std=0.02)
        self.register_buffer("relative_index", relative_position_index(agents, window), persistent=False)

    def bias(self, agents: int | Tensor) -> Tensor:
        """[heads, T, T] bias for the first ``agents`` slots, or for the given slot ids ([n] long tensor)."""
        p2 = self.window**2
        if isinstance(agents, int):
            if agents > self.agents:
                raise ValueError(f"{agents} agents > table size {self.agents}")
            idx = self.relative_index[: agents * p2, : agents * p2]
        else:
            if agents.numel() and int(agents.max()) >= self.agents:
                raise ValueError(f"agent slot {int(agents.max())} >= table size {self.agents}")
            tok = (agents[:, None] * p2 + torch.arange(p2, device=agents.device)).flatten()  # [T]
            idx = self.relative_index[tok[:, None], tok[None, :]]
        return self.relative_bias_table[idx].permute(2, 0, 1).contiguous()

    def forward(self, x: Tensor, agents: int | Tensor, key_mask: Tensor | None = None) -> Tensor:
        """x [..., T, C]: T = n*P*P tokens of a fused window of n agents, ``agents`` = n (slots 0..n-1) or
        the [n] slot ids the tokens belong to (for relative offsets); key_mask [..., T] bool (False = ignore)."""
        *lead, t, c = x.shape
        d = c // self.heads
        q, k, v = self.qkv(x).reshape(-1, t, 3, self.heads, d).permute(2, 0, 3, 1, 4)  # 3 x [G, h, T, d]
        g = q.shape[0]
        bias = self.bias(agents)  # [h, T, T]
        if key_mask is not None and not bool(key_mask.all()):
            # -inf on absent keys: [G, h, T, T] = bias + (0 | -inf per key)
            neg = torch.zeros(key_mask.shape, dtype=x.dtype, device=x.device).masked_fill(~key_mask, float("-inf"))
            mask = bias[None] + neg.reshape(g, 1, 1, t)
        else:
            mask = bias[None].expand(g, -1, -1, -1)
        # softmax(Q K^T / sqrt(d) + B) V, Eq. 2 (4D inputs take PyTorch's fused CPU kernel)
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=self.scale)  # [G, h, T, d]
        return self.proj(out.transpose(1, 2).reshape(*lead, t, c))


class FAXSelfAttention(nn.Module):
    """FAX-SA block: Eq. 5 (local, Fused-Block) followed by Eq. 6 (global, Fused-Grid).

    Pre-LayerNorm residual attention and MLP; window size = grid size = ``window``.
    Input/output ``[B, N, H, W, C]``; ``token_mask`` ``[B, N, H, W]`` bool marks tokens that may be
    attended to (absent agents / padding False). Masked tokens still get (meaningless) outputs.
    ``agent_ids`` ([N] long) gives the slot index of each of the N maps when they are a subset of the
    slots (relative agent offsets use slot indices); default 0..N-1.
    """

    def __init__(self, dim: int, heads: int, window: int, mlp_dim: int, agents: int) -> None:
        super().__init__()
        self.window = window
        self.norm1 = nn.LayerNorm(dim)
        self.local_attn = RelativeAttention3D(dim, heads, agents, window)
        self.norm2 = nn.LayerNorm(dim)
        self.local_mlp = Mlp(dim, mlp_dim)
        self.norm3 = nn.LayerNorm(dim)
        self.global_attn = RelativeAttention3D(dim, heads, agents, window)
        self.norm4 = nn.LayerNorm(dim)
        self.global_mlp = Mlp(dim, mlp_dim)

    def _attend(
        self, x: Tensor, attn: RelativeAttention3D, mode: str, mask: Tensor | None, agents: int | Tensor
    ) -> Tensor:
        _, n, h, w, _ = x.shape
        p = self.window
        xw = partition(x, p, mode)  # [B, G, N*P*P, C]
        mw = None if mask is None else partition(mask[..., None], p, mode)[..., 0]  # [B, G, N*P*P]
        return unpartition(attn(xw, agents, mw), p, mode, n, h, w)

    def forward(
        self, x: Tensor, token_mask: Tensor | None = None, agent_ids: Tensor | None = None
    ) -> Tensor:  # [B, N, H, W, C] -> same
        agents: int | Tensor = x.shape[1] if agent_ids is None else agent_ids
        x = x + self._attend(self.norm1(x), self.local_attn, "block", token_mask, agents)  # Eq. 5
        x = x + self.local_mlp(self.norm2(x))
        x = x + self._attend(self.norm3(x), self.global_attn, "grid", token_mask, agents)  # Eq. 6
        return x + self.global_mlp(self.norm4(x))


# --------------------------------------------------------------------------------------------------
# FAX cross-attention (SinBEVT): BEV-query windows attend to image windows of all cameras
# --------------------------------------------------------------------------------------------------


class CameraWindowAttention(nn.Module):
    """Multi-head cross attention from BEV windows to the matching image windows of all M cameras.

    Following CVT/CoBEVT, the BEV query is camera-aware: camera m's query (BEV feature + that camera's
    positional embedding) is compared only with camera m's keys, and one softmax runs jointly over all
    cameras' keys (Eq. 1 over the concatenated M*Tk keys). Queries, keys and values are pre-LayerNormed.
    No relative bias: BEV and image tokens live in different spaces; position comes from the embeddings.
    """

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} not divisible by heads {heads}")
        self.heads = heads
        self.scale = (dim // heads) ** -0.5
        self.norm_q = nn.LayerNorm(dim)
        self.norm_k = nn.LayerNorm(dim)
        self.norm_v = nn.LayerNorm(dim)
        self.to_q = nn.Linear(dim, dim)
        self.to_k = nn.Linear(dim, dim)
        self.to_v = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, q: Tensor, k: Tensor, v: Tensor) -> Tensor:
        """q [B, G, M, Tq, C], k/v [B, G, M, Tk, C] -> [B, G, Tq, C]."""
        b, g, m, tq, c = q.shape
        tk = k.shape[3]
        h, d = self.heads, c // self.heads
        q = self.to_q(self.norm_q(q)).reshape(b, g, m, tq, h, d)
        k = self.to_k(self.norm_k(k)).reshape(b, g, m, tk, h, d)
        v = self.to_v(self.norm_v(v)).reshape(b, g, m, tk, h, d)
        # camera m's query vs camera m's keys; one softmax over all cameras' keys (M * Tk)
        logits = torch.einsum("bgmqhd,bgmkhd->bghqmk", q * self.scale, k)  # [B, G, h, Tq, M, Tk]
        att = logits.reshape(b, g, h, tq, m * tk).softmax(dim=-1).reshape(b, g, h, tq, m, tk)
        out = torch.einsum("bghqmk,bgmkhd->bgqhd", att, v)  # [B, G, Tq, h, d]
        return self.proj(out.reshape(b, g, tq, c))


class FAXCrossAttention(nn.Module):
    """FAX-CA (SinBEVT, Table A2): local (Fused-Block) then global (Fused-Grid) BEV-to-image attention.

    BEV map H x W uses window/grid ``bev_window``; image features h x w use ``feat_window``; the number
    of groups must match, (H/bev_window)(W/bev_window) == (h/feat_window)(w/feat_window), so BEV group g
    pairs with image group g of every camera (local: co-located windows; global: dilated grids with the
    same offset). Each branch: x <- x + Attn(...); x <- x + MLP(LN(x)) (Eq. 5/6 with cross attention).
    """

    def __init__(self, dim: int, heads: int, bev_window: int, feat_window: int, mlp_dim: int) -> None:
        super().__init__()
        self.bev_window = bev_window
        self.feat_window = feat_window
        self.local_attn = CameraWindowAttention(dim, heads)
        self.local_norm = nn.LayerNorm(dim)
        self.local_mlp = Mlp(dim, mlp_dim)
        self.global_attn = CameraWindowAttention(dim, heads)
        self.global_norm = nn.LayerNorm(dim)
        self.global_mlp = Mlp(dim, mlp_dim)

    def _attend(self, x: Tensor, bev_pos: Tensor, key: Tensor, val: Tensor, mode: str) -> Tensor:
        b, hq, wq, c = x.shape
        m = bev_pos.shape[1]
        pq, pf = self.bev_window, self.feat_window
        q = x[:, None] + bev_pos  # [B, M, Hq, Wq, C] camera-aware queries
        qw = partition(q, pq, mode).reshape(b, -1, m, pq * pq, c)  # [B, G, M, Pq^2, C]
        kw = partition(key, pf, mode)
        vw = partition(val, pf, mode)
        g = qw.shape[1]
        if kw.shape[1] != g:
            raise ValueError(f"BEV groups {g} != image groups {kw.shape[1]}: check window sizes")
        kw = kw.reshape(b, g, m, pf * pf, c)
        vw = vw.reshape(b, g, m, pf * pf, c)
        attn = self.local_attn if mode == "block" else self.global_attn
        out = attn(qw, kw, vw)  # [B, G, Pq^2, C]
        return unpartition(out, pq, mode, 1, hq, wq)[:, 0]  # [B, Hq, Wq, C]

    def forward(self, x: Tensor, bev_pos: Tensor, key: Tensor, val: Tensor) -> Tensor:
        """x [B, Hq, Wq, C] BEV features; bev_pos [B, M, Hq, Wq, C]; key/val [B, M, h, w, C] -> [B, Hq, Wq, C]."""
        x = x + self._attend(x, bev_pos, key, val, "block")
        x = x + self.local_mlp(self.local_norm(x))
        x = x + self._attend(x, bev_pos, key, val, "grid")
        return x + self.global_mlp(self.global_norm(x))


def trunc_normal_init(module: nn.Module, std: float = 0.02) -> None:
    """Transformer-style init for Linear layers (truncated normal weights, zero bias)."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.trunc_normal_(m.weight, std=std)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


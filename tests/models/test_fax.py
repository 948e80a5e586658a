"""FAX attention (CoBEVT supp. Eq. 2-6): partitions, relative bias table/index, blocks."""

from __future__ import annotations

import pytest
import torch

from models.fax import (
    CameraWindowAttention,
    FAXCrossAttention,
    FAXSelfAttention,
    RelativeAttention3D,
    fused_block,
    fused_grid,
    fused_unblock,
    fused_ungrid,
    relative_position_index,
)


def coord_map(n: int, h: int, w: int) -> torch.Tensor:
    """[N, H, W, 3] whose entries are their own (n, row, col)."""
    nn_, hh, ww = torch.meshgrid(torch.arange(n), torch.arange(h), torch.arange(w), indexing="ij")
    return torch.stack([nn_, hh, ww], dim=-1)


@pytest.mark.parametrize("lead", [(), (2,), (2, 3)])
def test_block_and_grid_round_trip_exact(lead: tuple[int, ...]) -> None:
    x = torch.randn(*lead, 3, 16, 24, 5)
    blk = fused_block(x, 8)
    assert blk.shape == (*lead, 2 * 3, 3 * 8 * 8, 5)  # (HW/P^2, N*P^2, C), Eq. 3
    assert torch.equal(fused_unblock(blk, 8, 3, 16, 24), x)
    grd = fused_grid(x, 4)
    assert grd.shape == (*lead, 4 * 6, 3 * 4 * 4, 5)  # (HW/G^2, N*G^2, C), Eq. 4
    assert torch.equal(fused_ungrid(grd, 4, 3, 16, 24), x)


def test_fused_block_window_is_the_n_p_p_neighbourhood() -> None:
    n, h, w, p = 3, 8, 12, 4
    blk = fused_block(coord_map(n, h, w), p)  # [(H/P)(W/P), N*P*P, 3]
    for a in range(h // p):
        for b in range(w // p):
            win = blk[a * (w // p) + b]
            expect = coord_map(n, p, p) + torch.tensor([0, a * p, b * p])  # agent n, rows aP+i, cols bP+j
            assert torch.equal(win, expect.reshape(n * p * p, 3))
    # every agent's P x P patch of window (1, 2) lies in that window, nothing else
    win = blk[1 * (w // p) + 2]
    assert set(map(tuple, win.tolist())) == {(k, r, c) for k in range(n) for r in range(4, 8) for c in range(8, 12)}


def test_fused_grid_group_is_dilated_n_g_g_grid() -> None:
    n, h, w, g = 2, 8, 12, 4
    grd = fused_grid(coord_map(n, h, w), g)  # [(H/G)(W/G), N*G*G, 3]
    sh, sw = h // g, w // g
    for s in range(sh):
        for t in range(sw):
            got = grd[s * sw + t].reshape(n, g, g, 3)
            for k in range(n):
                for u in range(g):
                    for v in range(g):
                        assert got[k, u, v].tolist() == [k, s + u * sh, t + v * sw]


def test_bias_table_size_and_index() -> None:
    n, p, heads = 3, 4, 2
    attn = RelativeAttention3D(dim=8, heads=heads, agents=n, window=p)
    span = 2 * p - 1
    assert attn.relative_bias_table.shape == ((2 * n - 1) * span * span, heads)
    idx = attn.relative_index
    assert idx.shape == (n * p * p, n * p * p)

    def tok(a: int, i: int, j: int) -> int:
        return a * p * p + i * p + j

    def entry(da: int, di: int, dj: int) -> int:
        return ((da + n - 1) * span + di + p - 1) * span + dj + p - 1

    assert idx[tok(0, 0, 0), tok(0, 0, 0)] == entry(0, 0, 0)
    assert idx[tok(1, 2, 3), tok(0, 0, 0)] == entry(1, 2, 3)
    assert idx[tok(0, 0, 0), tok(2, 3, 3)] == entry(-2, -3, -3)  # smallest offsets -> row 0
    assert entry(-2, -3, -3) == 0 and entry(2, 3, 3) == attn.relative_bias_table.shape[0] - 1
    # equal offsets share an entry, different offsets do not
    assert idx[tok(1, 2, 3), tok(0, 1, 1)] == idx[tok(2, 3, 2), tok(1, 2, 0)] == entry(1, 1, 2)
    assert idx[tok(1, 2, 3), tok(0, 1, 1)] != idx[tok(1, 2, 3), tok(0, 1, 2)]
    assert idx.unique().numel() == attn.relative_bias_table.shape[0]  # bijection offsets <-> entries
    assert torch.equal(idx, relative_position_index(n, p))
    # the gathered bias reads the table; fewer agents use the leading block (actual offsets)
    bias = attn.bias(n)
    assert torch.equal(bias[1, tok(1, 2, 3), tok(0, 0, 0)], attn.relative_bias_table[entry(1, 2, 3), 1])
    assert torch.equal(attn.bias(2), bias[:, : 2 * p * p, : 2 * p * p])
    # a subset of slots (agents 0 and 2 present) keeps their real offsets
    keep = torch.cat([torch.arange(0, p * p), torch.arange(2 * p * p, 3 * p * p)])
    assert torch.equal(attn.bias(torch.tensor([0, 2])), bias[:, keep][:, :, keep])


def test_relative_attention_key_mask_removes_tokens() -> None:
    torch.manual_seed(0)
    attn = RelativeAttention3D(dim=8, heads=2, agents=2, window=2)
    x = torch.randn(3, 8, 8)  # [groups, N*P*P, C]
    mask = torch.ones(3, 8, dtype=torch.bool)
    mask[:, 4:] = False  # agent 1 absent
    y1 = attn(x, 2, mask)
    x2 = x.clone()
    x2[:, 4:] = torch.randn(3, 4, 8) * 50
    y2 = attn(x2, 2, mask)
    assert torch.allclose(y1[:, :4], y2[:, :4], atol=1e-6)
    # agent 0 alone with the 1-agent bias gives the same result as masking agent 1 out
    torch.testing.assert_close(attn(x[:, :4], 1), y1[:, :4], atol=1e-6, rtol=1e-5)


def test_fax_self_attention_block_shape_and_grad() -> None:
    blk = FAXSelfAttention(dim=16, heads=4, window=4, mlp_dim=32, agents=4)
    x = torch.randn(2, 3, 8, 8, 16, requires_grad=True)
    y = blk(x)
    assert y.shape == x.shape
    y.square().mean().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert blk.local_attn.relative_bias_table.grad.abs().sum() > 0
    assert blk.global_attn.relative_bias_table.grad.abs().sum() > 0


def test_camera_window_attention_joint_softmax_over_cameras() -> None:
    torch.manual_seed(0)
    attn = CameraWindowAttention(dim=8, heads=2)
    b, g, m, tq, tk, c = 1, 2, 3, 4, 5, 8
    q, k, v = torch.randn(b, g, m, tq, c), torch.randn(b, g, m, tk, c), torch.randn(b, g, m, tk, c)
    out = attn(q, k, v)
    # reference: per head, logits q_m . k_m for every camera, one softmax over all M*Tk keys
    qq = attn.to_q(attn.norm_q(q)).reshape(b, g, m, tq, 2, 4)
    kk = attn.to_k(attn.norm_k(k)).reshape(b, g, m, tk, 2, 4)
    vv = attn.to_v(attn.norm_v(v)).reshape(b, g, m, tk, 2, 4)
    ref = torch.zeros(b, g, tq, 2, 4)
    for gi in range(g):
        for h in range(2):
            logits = torch.cat([qq[0, gi, mi, :, h] @ kk[0, gi, mi, :, h].T for mi in range(m)], dim=1) / 2.0
            vals = torch.cat([vv[0, gi, mi, :, h] for mi in range(m)], dim=0)
            ref[0, gi, :, h] = logits.softmax(-1) @ vals
    torch.testing.assert_close(out, attn.proj(ref.reshape(b, g, tq, c)), atol=1e-5, rtol=1e-5)


def test_fax_cross_attention_local_branch_is_windowed() -> None:
    torch.manual_seed(0)
    ca = FAXCrossAttention(dim=8, heads=2, bev_window=4, feat_window=2, mlp_dim=16)
    b, m = 1, 2
    x = torch.randn(b, 8, 8, 8)  # BEV 8x8 -> 2x2 windows of 4x4
    pos = torch.randn(b, m, 8, 8, 8)
    key, val = torch.randn(b, m, 4, 4, 8), torch.randn(b, m, 4, 4, 8)  # features 4x4 -> 2x2 windows of 2x2
    y = ca._attend(x, pos, key, val, "block")
    key2, val2 = key.clone(), val.clone()
    key2[:, :, :2, :2] += torch.randn(b, m, 2, 2, 8)  # image window (0, 0), all cameras
    val2[:, :, :2, :2] += torch.randn(b, m, 2, 2, 8)
    y2 = ca._attend(x, pos, key2, val2, "block")
    changed = (y2 - y).abs().amax(-1)[0] > 1e-6  # [8, 8]
    assert changed[:4, :4].all() and not changed[4:].any() and not changed[:, 4:].any()
    assert ca(x, pos, key, val).shape == x.shape
    with pytest.raises(ValueError, match=r"BEV groups 4 != image groups 16: check window sizes"):
        ca(x, pos, torch.randn(b, m, 8, 8, 8), torch.randn(b, m, 8, 8, 8))  # 16 image windows vs 4 BEV

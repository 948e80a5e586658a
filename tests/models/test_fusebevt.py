"""FuseBEVT (CoBEVT Table A2): shapes, masking of absent agents, agent-order behaviour, gradients."""

from __future__ import annotations

import pytest
import torch

from models.fusion.cobevt import FuseBEVT


def make(channels: int = 16, **kw: int) -> FuseBEVT:
    torch.manual_seed(0)
    return FuseBEVT(channels, heads=kw.pop("heads", 2), window=kw.pop("window", 4), **kw).eval()


def test_table_a2_shapes() -> None:
    torch.manual_seed(0)
    m = FuseBEVT(128, heads=4, window=8, blocks=3, mlp_dim=256).eval()
    x = torch.randn(1, 4, 128, 32, 32)  # N x 32 x 32 x 128
    shapes = m.stage_shapes((x, torch.ones(1, 4, dtype=torch.bool)))
    assert shapes == [
        ("blocks.0", (1, 4, 32, 32, 128)),
        ("blocks.1", (1, 4, 32, 32, 128)),
        ("blocks.2", (1, 4, 32, 32, 128)),
        ("head", (1, 128, 32, 32)),  # fused 32 x 32 x 128
    ]
    blk = m.blocks[0]
    assert blk.local_attn.relative_bias_table.shape == ((2 * 8 - 1) * 15 * 15, 4)  # max_agents = 8
    assert blk.global_attn.relative_bias_table.shape == ((2 * 8 - 1) * 15 * 15, 4)


@pytest.mark.parametrize("hw", [(16, 16), (14, 11)])  # (14, 11) exercises the padding path
def test_masked_agents_have_no_influence(hw: tuple[int, int]) -> None:
    m = make()
    h, w = hw
    x = torch.randn(2, 5, 16, h, w)
    valid = torch.tensor([[1, 0, 1, 0, 1], [1, 1, 0, 0, 0]], dtype=torch.bool)
    with torch.no_grad():
        y = m(x, valid)
        x2 = x.clone()
        x2[~valid] = torch.randn_like(x2[~valid]) * 100.0
        y2 = m(x2, valid)
    assert y.shape == (2, 16, h, w)
    assert torch.isfinite(y).all()
    torch.testing.assert_close(y, y2, atol=1e-5, rtol=0)


def test_trailing_absent_slots_equal_fewer_agents() -> None:
    m = make()
    x = torch.randn(1, 4, 16, 8, 8)
    with torch.no_grad():
        y_masked = m(x, torch.tensor([[True, True, False, False]]))
        y_two = m(x[:, :2], torch.tensor([[True, True]]))
    torch.testing.assert_close(y_masked, y_two, atol=1e-5, rtol=1e-5)


def test_ego_slot_is_always_present() -> None:
    m = make()
    x = torch.randn(1, 3, 16, 8, 8)
    with torch.no_grad():
        a = m(x, torch.tensor([[False, True, False]]))
        b = m(x, torch.tensor([[True, True, False]]))
    torch.testing.assert_close(a, b)


def test_agent_permutation() -> None:
    """The relative bias over agent offsets makes FuseBEVT order-dependent for non-ego agents; with a bias
    that only distinguishes "same agent" from "other agent" it is exactly permutation invariant."""
    m = make(max_agents=4)
    x = torch.randn(1, 4, 16, 8, 8)
    valid = torch.ones(1, 4, dtype=torch.bool)
    perm = [0, 3, 1, 2]
    with torch.no_grad():
        for blk in m.blocks:
            for attn in (blk.local_attn, blk.global_attn):
                attn.relative_bias_table.normal_()  # a trained-looking, agent-dependent bias
        y, y_perm = m(x, valid), m(x[:, perm], valid)
        assert (y - y_perm).abs().max() > 1e-4  # documented: not invariant in general
        for blk in m.blocks:
            for attn in (blk.local_attn, blk.global_attn):
                t = attn.relative_bias_table.view(2 * 4 - 1, -1, attn.heads)  # [agent offset, (2P-1)^2, h]
                other = t[4].clone()  # offset +1 stands for "another agent"
                t[:] = other
                t[4 - 1] = torch.randn_like(other)  # offset 0: same agent
        y, y_perm = m(x, valid), m(x[:, perm], valid)
    torch.testing.assert_close(y, y_perm, atol=1e-5, rtol=1e-5)


def test_gradients_flow_and_masked_slots_get_none() -> None:
    m = make()
    m.train()
    x = torch.randn(1, 3, 16, 8, 8, requires_grad=True)
    valid = torch.tensor([[True, False, True]])
    y = m(x, valid)
    y.square().mean().backward()
    assert torch.isfinite(x.grad).all()
    assert x.grad[0, 0].abs().sum() > 0 and x.grad[0, 2].abs().sum() > 0
    assert x.grad[0, 1].abs().sum() == 0
    for name, p in m.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_too_many_agents_rejected() -> None:
    m = make(max_agents=2)
    with pytest.raises(ValueError, match=r"3 agent slots > max_agents 2"):
        m(torch.randn(1, 3, 16, 8, 8), torch.ones(1, 3, dtype=torch.bool))


def test_masked_path_equals_dropped_slots_path() -> None:
    """Samples with different present agents take the -inf masking path; a batch where all samples have
    the same agents drops the absent slots. Both give the same result."""
    m = make()
    x = torch.randn(2, 4, 16, 8, 8)
    valid = torch.tensor([[True, False, True, True], [True, True, False, False]])
    with torch.no_grad():
        both = m(x, valid)
        for i in range(2):
            alone = m(x[i : i + 1], valid[i : i + 1])
            torch.testing.assert_close(both[i : i + 1], alone, atol=1e-5, rtol=1e-5)


def test_head_starts_as_the_identity_and_learns() -> None:
    # the zoo fine-tunes heads pretrained on the encoder's raw features: FuseBEVT must hand them that space
    m = FuseBEVT(16, heads=2, window=4)
    x = torch.randn(2, 5, 6, 16)  # [B, H, W, C] agent-reduced map
    assert torch.equal(m.head(x), x.permute(0, 3, 1, 2))
    m.head(x).square().sum().backward()
    assert m.head.update.weight.grad.abs().sum() > 0  # zero-initialised, not frozen

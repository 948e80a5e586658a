from __future__ import annotations

import pytest
import torch

from models.compression import ChannelCompressor


def test_shapes_and_ratio_must_divide() -> None:
    c = ChannelCompressor(64, 8).eval()
    x = torch.randn(2, 64, 32, 32)
    z = c.compress(x)
    assert z.shape == (2, 8, 32, 32)
    assert c.decompress(z).shape == x.shape
    with pytest.raises(ValueError, match="must divide"):
        ChannelCompressor(64, 48)


def test_learns_to_reconstruct_low_rank_features() -> None:
    torch.manual_seed(0)
    basis = torch.randn(4, 32)
    x = torch.relu(torch.einsum("bkhw,kc->bchw", torch.randn(2, 4, 4, 4), basis))  # rank-4 features
    c = ChannelCompressor(32, 8)
    opt = torch.optim.Adam(c.parameters(), lr=2e-2)
    first = None
    for _ in range(150):
        loss = torch.nn.functional.mse_loss(c(x), x)
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < first / 10

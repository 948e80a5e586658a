"""FeatureExtrapolation (receiver-side latency compensation): exact identity at steps 0 and untrained, the
previous message aligned into the newer one's frame, gradients reach only its own parameters."""

from __future__ import annotations

import torch

from models.extrapolation import FeatureExtrapolation, align_previous, compensate, extrapolation_steps

C, F, S = 8, 16, 100.0  # channels, cells, metres
CELL = S / F


def _trained(channels: int = C) -> FeatureExtrapolation:
    """A module whose last convolution is no longer zero (as after training)."""
    torch.manual_seed(0)
    m = FeatureExtrapolation(channels)
    torch.nn.init.normal_(m.net[-1].weight, std=0.1)
    torch.nn.init.normal_(m.net[-1].bias, std=0.1)
    return m


def test_steps_zero_returns_new_exactly() -> None:
    new, old = torch.randn(3, C, F, F), torch.randn(3, C, F, F)
    m = _trained()
    assert torch.equal(m(new, old, torch.zeros(3)), new)
    out = m(new, old, torch.tensor([0.0, 2.0, 0.0]))  # rows at 0 stay exact beside a moving one
    assert torch.equal(out[0], new[0]) and torch.equal(out[2], new[2]) and not torch.equal(out[1], new[1])


def test_untrained_module_is_the_identity_for_any_steps() -> None:
    new, old = torch.randn(4, C, F, F), torch.randn(4, C, F, F)
    m = FeatureExtrapolation(C)
    assert torch.count_nonzero(m.net[-1].weight) == 0 and torch.count_nonzero(m.net[-1].bias) == 0
    for steps in ([1.0, 2.0, 3.5, 5.0], [0.0, 0.5, 10.0, 1.0]):
        assert torch.equal(m(new, old, torch.tensor(steps)), new)


def test_output_is_first_order_in_steps() -> None:
    new, old = torch.randn(1, C, F, F), torch.randn(1, C, F, F)
    m = _trained()
    one, three = m(new, old, torch.tensor([1.0])), m(new, old, torch.tensor([3.0]))
    torch.testing.assert_close(three - new, 3 * (one - new), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(one - new, m.derivative(new, old))


def test_gradients_reach_the_untrained_last_layer() -> None:
    new, old = torch.randn(2, C, F, F), torch.randn(2, C, F, F)
    m = FeatureExtrapolation(C)
    m(new, old, torch.tensor([1.0, 2.0])).square().sum().backward()
    assert m.net[-1].weight.grad is not None and m.net[-1].weight.grad.abs().sum() > 0


def test_align_previous_zero_pose_is_the_identity() -> None:
    old = torch.randn(2, C, F, F)
    assert torch.equal(align_previous(old, torch.zeros(2, 3), S), old)
    assert torch.equal(align_previous(old, torch.zeros(2, 3), S, fill=torch.randn(2, C, F, F)), old)


def test_align_previous_translation_shifts_by_whole_cells() -> None:
    # The older capture 2 cells ahead (+x) and 3 cells left (+y) of the newer one: what the old map had at
    # row r, column c lies 2 rows up (front = row 0) and 3 columns left (left = column 0) on the newer grid.
    old = torch.randn(1, C, F, F)
    rel = torch.tensor([[2 * CELL, 3 * CELL, 0.0]])
    out = align_previous(old, rel, S)
    torch.testing.assert_close(out[..., : F - 2, : F - 3], old[..., 2:, 3:], rtol=1e-5, atol=1e-5)
    assert torch.count_nonzero(out[..., F - 2:, :]) == 0 and torch.count_nonzero(out[..., :, F - 3:]) == 0
    fill = torch.full_like(old, 7.0)
    filled = align_previous(old, rel, S, fill=fill)  # uncovered cells from `fill`
    assert torch.all(filled[..., F - 2:, :] == 7.0) and torch.all(filled[..., :, F - 3:] == 7.0)
    torch.testing.assert_close(filled[..., : F - 2, : F - 3], old[..., 2:, 3:], rtol=1e-5, atol=1e-5)


def test_compensate_of_a_static_scene_seen_by_a_moving_sender() -> None:
    # The same static scene seen from two poses 1 cell apart: aligned, the two messages agree, so the
    # derivative net sees zero change (its input half new - old_aligned is 0 inside the overlap).
    torch.manual_seed(1)
    world = torch.randn(1, C, F + 1, F)
    new, old = world[..., :F, :], world[..., 1:, :]  # old captured one cell behind (-x): its rows shifted by 1
    aligned = align_previous(old, torch.tensor([[-CELL, 0.0, 0.0]]), S, fill=new)
    torch.testing.assert_close(aligned, new, rtol=1e-5, atol=1e-5)
    m = FeatureExtrapolation(C)
    out = compensate(m, new.contiguous(), old.contiguous(), torch.tensor([[-CELL, 0.0, 0.0]]), torch.tensor([2.0]), S)
    assert torch.equal(out, new)


def test_extrapolation_steps() -> None:
    assert extrapolation_steps(0.2, 0.1) == 2.0 and extrapolation_steps(0.3, 0.0) == 0.0

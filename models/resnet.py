"""ResNet-34 image encoder (BasicBlock), written here because there is no torchvision on this machine.

Naming follows CoBEVT supp. Table A2, not torchvision. Table A2's "ResNet34-layer1/2/3" outputs are
N x M x 64x64x128, 32x32x256, 16x16x512 for 512x512 images, i.e. output strides 8/16/32 with
128/256/512 channels: those are torchvision's ``layer2``/``layer3``/``layer4`` (the CoBEVT code picks
feature indices 1, 2, 3). So here:

    stem    conv7x7/2 + BN + ReLU + maxpool/2          stride 4,   64 ch   (torchvision conv1..maxpool)
    layer0  3 BasicBlocks                              stride 4,   64 ch   (torchvision layer1)
    layer1  4 BasicBlocks, first with stride 2         stride 8,  128 ch   (torchvision layer2)
    layer2  6 BasicBlocks, first with stride 2         stride 16, 256 ch   (torchvision layer3)
    layer3  3 BasicBlocks, first with stride 2         stride 32, 512 ch   (torchvision layer4)

``forward`` returns ``[layer1, layer2, layer3]``. The full ResNet-34 block stack (3, 4, 6, 3) is kept;
``width`` scales every stage's channels and ``blocks`` sets blocks per stage for the tiny preset.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

RESNET34_BLOCKS: tuple[int, int, int, int] = (3, 4, 6, 3)
RESNET34_CHANNELS: tuple[int, int, int, int] = (64, 128, 256, 512)


class BasicBlock(nn.Module):
    """ResNet BasicBlock: two 3x3 convs with BN, identity (or 1x1 projection) shortcut, ReLU."""

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or in_ch != out_ch:
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, 1, stride=stride, bias=False), nn.BatchNorm2d(out_ch)
            )

    def forward(self, x: Tensor) -> Tensor:  # [B, Cin, H, W] -> [B, Cout, H/s, W/s]
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.relu(y + self.shortcut(x))


def _make_layer(in_ch: int, out_ch: int, blocks: int, stride: int) -> nn.Sequential:
    layers = [BasicBlock(in_ch, out_ch, stride)]
    layers += [BasicBlock(out_ch, out_ch, 1) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


class ResNet(nn.Module):
    """ResNet-34 feature extractor returning the Table A2 ``layer1``, ``layer2``, ``layer3`` maps.

    Args:
        width: channel multiplier (1.0 = ResNet-34: 64/128/256/512 channels).
        blocks: BasicBlocks per stage (layer0..layer3); (3, 4, 6, 3) = ResNet-34.
    """

    def __init__(self, width: float = 1.0, blocks: Sequence[int] = RESNET34_BLOCKS) -> None:
        super().__init__()
        if len(blocks) != 4 or min(blocks) < 1:
            raise ValueError(f"blocks must be 4 positive ints, got {tuple(blocks)}")
        ch = [max(8, int(round(c * width))) for c in RESNET34_CHANNELS]
        self.stem = nn.Sequential(
            nn.Conv2d(3, ch[0], 7, stride=2, padding=3, bias=False),
            nn.BatchNorm2d(ch[0]),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, stride=2, padding=1),
        )
        self.layer0 = _make_layer(ch[0], ch[0], blocks[0], 1)
        self.layer1 = _make_layer(ch[0], ch[1], blocks[1], 2)
        self.layer2 = _make_layer(ch[1], ch[2], blocks[2], 2)
        self.layer3 = _make_layer(ch[2], ch[3], blocks[3], 2)
        self.out_channels: tuple[int, int, int] = (ch[1], ch[2], ch[3])
        self.strides: tuple[int, int, int] = (8, 16, 32)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: Tensor) -> list[Tensor]:
        """x [B, 3, H, W] (normalised) -> [layer1 [B,C1,H/8,W/8], layer2 [B,C2,H/16,W/16], layer3 [.., /32]]."""
        x = self.layer0(self.stem(x))
        f1 = self.layer1(x)
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        return [f1, f2, f3]


def resnet34(width: float = 1.0, blocks: Sequence[int] = RESNET34_BLOCKS) -> ResNet:
    """ResNet-34 (Table A2 image encoder); ``width``/``blocks`` shrink it for the tiny preset."""
    return ResNet(width=width, blocks=blocks)


def record_stage_shapes(
    module: nn.Module, stage_names: Sequence[str], run: Callable[[], object], skip_missing: bool = False
) -> list[tuple[str, tuple[int, ...]]]:
    """Run ``run()`` with forward hooks on the named submodules; return (name, output shape) in order.

    A submodule called several times (e.g. per camera) reports its last output. Tensor outputs only;
    for tuple/list outputs the first tensor is reported, for dict outputs the first value. A name that is
    no submodule is a KeyError, or left out with ``skip_missing`` (`v2vsim models` on a plugin's module).
    """
    shapes: dict[str, tuple[int, ...]] = {}
    handles = []
    subs = dict(module.named_modules())
    for name in stage_names:
        if name not in subs:
            if skip_missing:
                continue
            raise KeyError(f"no submodule named {name!r}")

        def hook(_m: nn.Module, _inp: object, out: object, name: str = name) -> None:
            t = out[0] if isinstance(out, (tuple, list)) else out
            if isinstance(out, dict):
                t = next(iter(out.values()))
            if isinstance(t, Tensor):
                shapes[name] = tuple(t.shape)

        handles.append(subs[name].register_forward_hook(hook))
    try:
        with torch.no_grad():
            run()
    finally:
        for h in handles:
            h.remove()
    return [(n, shapes[n]) for n in stage_names if n in shapes]

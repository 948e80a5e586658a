"""models.heads + models.losses: Table A2 decoder, segmentation heads, anchor detection head."""

from __future__ import annotations

import math

import pytest
import torch

from models.build import build_heads
from models.heads import (
    AnchorTargetAssigner,
    BevHeads,
    decode_boxes,
    decode_detections,
    encode_boxes,
    flatten_det,
    make_anchors,
    segmentation_probabilities,
)
from models.losses import detection_loss, dynamic_target, segmentation_loss, sigmoid_focal_loss, static_target
from v2vsim.world.geometry import BevGrid


def test_table_a2_decoder_shapes_paper() -> None:
    heads = build_heads("lidar", "paper").eval()
    with torch.no_grad():
        s1, s2, s3 = heads.decoder(torch.randn(1, 128, 32, 32))
        out = heads(torch.randn(1, 128, 32, 32))
    assert s1.shape == (1, 128, 64, 64) and s2.shape == (1, 64, 128, 128) and s3.shape == (1, 32, 256, 256)
    assert out["dynamic"].shape == (1, 2, 256, 256) and out["static"].shape == (1, 3, 256, 256)
    assert out["det_cls"].shape == (1, 2, 128, 128) and out["det_reg"].shape == (1, 12, 128, 128)


def test_camera_heads_have_no_detection() -> None:
    heads = build_heads("camera", "tiny")
    assert heads.detection is None and set(heads(torch.randn(1, 64, 32, 32))) == {"dynamic", "static"}
    with pytest.raises(ValueError, match="modality"):
        build_heads("radar", "tiny")


def test_probabilities_road_includes_lane() -> None:
    dyn, sta = torch.randn(2, 2, 8, 8), torch.randn(2, 3, 8, 8)
    p = segmentation_probabilities(dyn, sta)
    soft = torch.softmax(sta, 1)
    torch.testing.assert_close(p["road"], soft[:, 1] + soft[:, 2])
    torch.testing.assert_close(p["lane"], soft[:, 2])
    torch.testing.assert_close(p["vehicle"], torch.softmax(dyn, 1)[:, 1])
    assert (p["road"] >= p["lane"]).all()


def test_targets_lane_precedence_and_seg_loss() -> None:
    road = torch.tensor([[[1, 1, 0]]])
    lane = torch.tensor([[[0, 1, 1]]])
    assert static_target(road, lane).tolist() == [[[1, 2, 2]]]
    t = dynamic_target(torch.tensor([[[1, 0, 1]]]), ignore=torch.tensor([[[0, 0, 1]]]))
    assert t.tolist() == [[[1, 0, -100]]]
    logits = torch.zeros(1, 2, 1, 3)
    assert segmentation_loss(logits, t).item() == pytest.approx(math.log(2))


def test_anchors_sit_on_bev_cell_centres() -> None:
    a = make_anchors(128, 100.0).view(128, 128, 2, 5)
    centres = torch.as_tensor(BevGrid(100.0, 128).cell_centres(), dtype=torch.float32)
    torch.testing.assert_close(a[:, :, 0, :2], centres)
    torch.testing.assert_close(a[0, 0, :, 4], torch.tensor([0.0, math.pi / 2]))


def test_box_code_round_trip_modulo_pi() -> None:
    anchors = torch.tensor([[0.0, 0.0, 4.5, 1.9, 0.0], [5.0, 5.0, 4.5, 1.9, math.pi / 2]])
    boxes = torch.tensor([[0.3, -0.2, 4.0, 2.0, 0.3], [5.5, 4.0, 5.0, 1.8, math.pi / 2 + 2.0]])
    dec = decode_boxes(encode_boxes(boxes, anchors), anchors)
    torch.testing.assert_close(dec[:, :4], boxes[:, :4], atol=1e-5, rtol=0)
    dyaw = torch.remainder(dec[:, 4] - boxes[:, 4] + math.pi / 2, math.pi) - math.pi / 2
    torch.testing.assert_close(dyaw, torch.zeros(2), atol=1e-5, rtol=0)
    zero = encode_boxes(anchors, anchors)
    torch.testing.assert_close(zero, torch.tensor([[0.0, 0, 0, 0, 0, 1]] * 2), atol=1e-6, rtol=0)


def test_assigner_and_decoder_recover_a_box() -> None:
    anchors = make_anchors(128, 100.0)
    gt = torch.tensor([[10.2, -5.1, 4.4, 1.9, 0.1], [-30.0, 20.0, 4.6, 2.0, 1.5]])
    targets = AnchorTargetAssigner(anchors)(gt)
    pos = targets.labels == 1
    assert pos.sum() >= 2 and (targets.labels == -1).any()
    # a perfect head: logits +10 on positives, regression = targets
    cls = torch.where(pos, 10.0, -10.0).view(1, 128, 128, 2).permute(0, 3, 1, 2)
    reg = targets.reg.view(1, 128, 128, 2, 6).permute(0, 3, 4, 1, 2).reshape(1, 12, 128, 128)
    c_f, r_f = flatten_det(cls, reg)
    assert torch.equal(c_f[0] > 0, pos) and torch.equal(r_f[0], targets.reg)
    boxes = decode_detections(cls, reg, anchors, score_threshold=0.5, nms_iou=0.3)[0]
    assert boxes.shape == (2, 6)
    got = boxes[boxes[:, 0].argsort(descending=True)]
    torch.testing.assert_close(got[:, :4], gt[:, :4], atol=1e-4, rtol=0)
    losses = detection_loss(cls, reg, targets.labels[None], targets.reg[None])
    assert losses["reg"].item() == pytest.approx(0.0, abs=1e-6) and losses["cls"].item() < 1e-4


def test_focal_loss_down_weights_easy_examples() -> None:
    easy = sigmoid_focal_loss(torch.tensor([5.0]), torch.tensor([1.0]))
    hard = sigmoid_focal_loss(torch.tensor([-5.0]), torch.tensor([1.0]))
    assert hard > 1000 * easy


def test_heads_accept_custom_sizes() -> None:
    h = BevHeads(32, (16, 8, 8), detection=True)
    out = h(torch.randn(2, 32, 16, 16))
    assert out["dynamic"].shape == (2, 2, 128, 128) and out["det_cls"].shape == (2, 2, 64, 64)


def test_heads_for_inference_compute_the_same_function() -> None:
    """BatchNorm folded into the decoder convs and channels-last layout: the run's heads, equal to
    the trained ones to float precision (with BatchNorm statistics that are not the identity)."""
    import copy

    torch.manual_seed(0)
    heads = BevHeads(16, (16, 8, 8), detection=True).train()
    with torch.no_grad():
        for _ in range(3):  # move the running statistics away from (0, 1)
            heads(torch.randn(2, 16, 8, 8) * 3 + 1)
    heads.eval()
    fast = copy.deepcopy(heads).for_inference()
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fast.modules())
    x = torch.randn(1, 16, 8, 8)
    with torch.no_grad():
        a, b = heads(x), fast(x)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-5, rtol=1e-5), (k, (a[k] - b[k]).abs().max())

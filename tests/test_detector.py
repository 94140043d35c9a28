"""Mask R-CNN detector: label map, builders, a few training steps, detections, ONNX export."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from torchvision.ops import FrozenBatchNorm2d, box_iou

from cosy_lite.bop.detections import Detections
from cosy_lite.nets.detector import (
    DETECTORS,
    Detector,
    DetectorConfig,
    LabelMap,
    detect,
    detector_losses,
)

H, W = 120, 160
OBJ_IDS = (1, 2, 5)
COLOURS = {1: (1.0, 0.0, 0.0), 2: (0.0, 1.0, 0.0), 5: (0.0, 0.0, 1.0)}
# Small, fast settings: 120x160 images kept at their size, few proposals, narrow FPN.
SMALL = dict(name="maskrcnn_resnet18_fpn", fpn_channels=64, mask_head_channels=64, box_head_size=256, min_size=H, max_size=W,
             rpn_pre_nms_top_n_train=200, rpn_post_nms_top_n_train=100,
             rpn_pre_nms_top_n_test=50, rpn_post_nms_top_n_test=20, box_batch_size_per_image=64)


def rectangles_image(seed: int, rects: list[tuple[int, tuple[int, int, int, int]]]) -> tuple[torch.Tensor, dict]:
    """Coloured rectangles (obj_id, x0, y0, x1, y1) on dark noise, with the torchvision target."""
    im = torch.rand(3, H, W, generator=torch.Generator().manual_seed(seed)) * 0.3
    masks = torch.zeros(len(rects), H, W, dtype=torch.bool)
    for k, (obj_id, (x0, y0, x1, y1)) in enumerate(rects):
        masks[k, y0:y1, x0:x1] = True
        im[:, masks[k]] = torch.tensor(COLOURS[obj_id]).view(3, 1)
    boxes = torch.tensor([r for _, r in rects], dtype=torch.float32)
    labels = LabelMap(OBJ_IDS).labels(torch.tensor([o for o, _ in rects]))
    return im, {"boxes": boxes, "labels": labels, "masks": masks.to(torch.uint8)}


def two_images() -> tuple[list[torch.Tensor], list[dict]]:
    a = rectangles_image(0, [(1, (10, 20, 60, 70)), (2, (80, 30, 140, 90)), (5, (40, 80, 100, 115))])
    b = rectangles_image(1, [(5, (5, 5, 50, 40)), (1, (90, 60, 150, 110))])
    return [a[0], b[0]], [a[1], b[1]]


def test_label_map_round_trip():
    lm = LabelMap((1, 2, 5, 8))
    assert lm.n_classes == 5
    assert lm.labels(torch.tensor([8, 1, 5])).tolist() == [4, 1, 3]
    assert lm.obj_ids_of(torch.tensor([4, 1, 3])).tolist() == [8, 1, 5]
    assert (lm.label(5), lm.obj_id(3)) == (3, 5)
    again = LabelMap.from_dict(lm.to_dict())
    assert again == lm and again.obj_ids == (1, 2, 5, 8)
    with pytest.raises(ValueError, match=r"\[3\]"):
        lm.labels(torch.tensor([1, 3]))
    with pytest.raises(ValueError, match="increasing"):
        LabelMap((2, 1))


def test_builders_use_trainable_norm_and_know_their_names():
    for name in DETECTORS:  # from scratch (the pretrained trunk's frozen parts: test_detector_pretrained.py)
        net = Detector(LabelMap(OBJ_IDS), DetectorConfig(name=name, fpn_channels=32, pretrained=False)).net
        assert not any(isinstance(m, FrozenBatchNorm2d) for m in net.modules()), name
        assert all(p.requires_grad for p in net.parameters()), name
        assert net.roi_heads.box_predictor.cls_score.out_features == 4
    group = Detector(LabelMap(OBJ_IDS), DetectorConfig(name="maskrcnn_resnet18_fpn", norm="group", fpn_channels=32)).net
    assert any(isinstance(m, torch.nn.GroupNorm) for m in group.modules())
    assert net.roi_heads.mask_head[0][0].out_channels == 256  # last net: torchvision's default widths
    with pytest.raises(ValueError, match="maskrcnn_resnet18_fpn"):
        Detector(LabelMap(OBJ_IDS), DetectorConfig(name="yolo"))


def test_meta_rebuilds_the_same_module():
    cfg = DetectorConfig(name="maskrcnn_mobilenet_v3_large_fpn", min_size=240, max_size=320)
    det = Detector(LabelMap((3, 7)), cfg)
    again = Detector.from_meta(det.meta())
    assert again.label_map == det.label_map and again.config == cfg
    again.load_state_dict(det.state_dict())  # strict: same architecture


def test_few_steps_lower_the_loss():
    torch.manual_seed(0)
    images, targets = two_images()
    model = Detector(LabelMap(OBJ_IDS), DetectorConfig(**SMALL)).train()
    opt = torch.optim.Adam(model.parameters(), lr=3e-4)
    totals = []
    for _ in range(8):
        losses = detector_losses(model, images, targets)
        assert set(losses) == {"loss_classifier", "loss_box_reg", "loss_mask", "loss_objectness",
                               "loss_rpn_box_reg", "total"}
        opt.zero_grad()
        losses["total"].backward()
        opt.step()
        totals.append(losses["total"].item())
    assert np.isfinite(totals).all()
    assert np.mean(totals[-3:]) < 0.6 * totals[0], totals
    with pytest.raises(ValueError, match="masks"):
        detector_losses(model, images[:1], [dict(targets[0], masks=targets[0]["masks"][:, :10])])
    with pytest.raises(ValueError, match="not obj_ids"):
        detector_losses(model, images[:1], [dict(targets[0], labels=torch.tensor([1, 2, 5]))])


def test_detect_returns_obj_ids_and_image_sized_masks():
    torch.manual_seed(0)
    model = Detector(LabelMap(OBJ_IDS), DetectorConfig(**SMALL, box_score_thresh=0.0, box_detections_per_img=10)).train()
    images, _ = two_images()
    dets = detect(model, [images[0], images[1][:, :100, :140]])
    assert model.training  # mode restored
    assert [type(d) for d in dets] == [Detections, Detections]
    assert len(dets[0]) == 10 and dets[0].masks.shape == (10, H, W) and dets[0].masks.dtype == torch.bool
    assert dets[1].masks.shape[1:] == (100, 140)
    assert set(dets[0].obj_ids.tolist()) <= set(OBJ_IDS)
    assert (dets[0].scores[:-1] >= dets[0].scores[1:]).all()


def test_onnx_export_matches_torch(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    torch.manual_seed(0)
    model = Detector(LabelMap(OBJ_IDS), DetectorConfig(**SMALL, box_score_thresh=0.0, box_detections_per_img=10)).eval()
    images, _ = two_images()
    path = tmp_path / "detector.onnx"
    with warnings.catch_warnings():  # the legacy exporter warns about traced size arithmetic
        warnings.simplefilter("ignore")
        torch.onnx.export(model.net, ([images[0]],), path, dynamo=False, opset_version=17, input_names=["image"],
                          output_names=["boxes", "labels", "scores", "masks"], dynamic_axes={"image": [1, 2]})
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for im in (images[1], torch.rand(3, 2 * H, 2 * W, generator=torch.Generator().manual_seed(3))):
        with torch.no_grad():
            ref = model.net([im])[0]
        boxes, labels, scores, masks = session.run(None, {"image": im.numpy()})
        assert len(boxes) == len(ref["boxes"]) == 10
        assert (labels == ref["labels"].numpy()).all()
        assert box_iou(ref["boxes"], torch.from_numpy(boxes)).diag().min() >= 0.99
        np.testing.assert_allclose(scores, ref["scores"].numpy(), atol=1e-4)
        assert masks.shape == tuple(ref["masks"].shape) == (10, 1, *im.shape[1:])


"""DetectionFilter: the score threshold and one object per image region, on hand-made detections."""

import pytest
import torch

from cosy_lite.bop.detections import Detections
from cosy_lite.inference.detection_filter import DetectionFilter, region_ious


def _boxes(*rows):
    b = torch.tensor([r[:4] for r in rows], dtype=torch.float32)
    return Detections(b, torch.tensor([r[4] for r in rows]), torch.tensor([r[5] for r in rows], dtype=torch.float32))


def test_threshold_keeps_scores_at_or_above_it_sorted():
    det = _boxes((0, 0, 10, 10, 1, 0.3), (50, 50, 60, 60, 2, 0.9), (0, 0, 5, 5, 3, 0.29999))
    out = DetectionFilter(min_score=0.3)(det)
    assert out.obj_ids.tolist() == [2, 1]
    assert DetectionFilter()(det).obj_ids.tolist() == [2, 1, 3]


def test_one_per_region_drops_the_weaker_class_on_the_same_object_only():
    # obj 1 and 2 on one object (boxes 1 px apart: IoU 9x9 / (100 + 100 - 81) = 0.68); obj 3
    # elsewhere; obj 4 overlapping obj 1 by IoU 6x6 / (200 - 36) = 0.22
    det = _boxes((0, 0, 10, 10, 2, 0.5), (1, 1, 11, 11, 1, 0.8), (100, 100, 120, 120, 3, 0.2), (5, 5, 15, 15, 4, 0.4))
    iou = region_ious(det)
    assert iou[0, 1] == pytest.approx(81 / 119)
    assert iou[1, 3] == pytest.approx(36 / 164)
    out = DetectionFilter(one_per_region=True)(det)
    assert out.obj_ids.tolist() == [1, 4, 3]
    assert DetectionFilter(one_per_region=True, region_iou=0.7)(det).obj_ids.tolist() == [1, 2, 4, 3]


def test_one_per_region_uses_masks_when_there_are_some():
    # the boxes coincide, the masks do not overlap: two objects side by side in one box
    m = torch.zeros(2, 20, 20, dtype=torch.bool)
    m[0, :, :10] = True
    m[1, :, 10:] = True
    det = Detections(torch.tensor([[0, 0, 20, 20], [0, 0, 20, 20]], dtype=torch.float32), torch.tensor([1, 2]),
                     torch.tensor([0.9, 0.8]), m)
    assert DetectionFilter(one_per_region=True)(det).obj_ids.tolist() == [1, 2]
    m[1] = m[0]
    assert DetectionFilter(one_per_region=True)(det).obj_ids.tolist() == [1]


@pytest.mark.parametrize("kw", [{"min_score": -0.1}, {"min_score": 1.5}, {"region_iou": 0.0}])
def test_bad_settings_are_refused(kw):
    with pytest.raises(ValueError):
        DetectionFilter(**kw)


def test_max_per_object_keeps_the_best_scored_of_each_object():
    det = Detections(boxes=torch.tensor([[0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10], [60, 0, 70, 10.0]]),
                     obj_ids=torch.tensor([1, 1, 2, 1]), scores=torch.tensor([0.5, 0.9, 0.4, 0.7]))
    assert DetectionFilter(max_per_object=1)(det).scores.tolist() == pytest.approx([0.9, 0.4])
    assert DetectionFilter(max_per_object=2)(det).scores.tolist() == pytest.approx([0.9, 0.7, 0.4])
    assert DetectionFilter(min_score=0.6, max_per_object=1)(det).scores.tolist() == pytest.approx([0.9])
    assert DetectionFilter()(det).scores.tolist() == pytest.approx([0.9, 0.7, 0.5, 0.4])

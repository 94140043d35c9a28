"""DetectionDataset on the hand-written BOP fixture: targets equal bbox_visib / mask_visib, the
visibility and area thresholds drop instances, empty images stay valid, lists for torchvision."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from bop_fixtures import GT, edit_json, scene_dir, write_tiny_bop

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.data.augmentation import AugmentationConfig, StrongAugmentation
from cosy_lite.data.backgrounds import BackgroundPool
from cosy_lite.data.detection_dataset import DetectionDataset, collate_detections, make_label_map, split_train_val
from cosy_lite.errors import BopFormatError
from cosy_lite.structures import DetectionBatch

SPLIT = "test"


@pytest.fixture()
def root(tmp_path: Path) -> Path:
    """The fixture (im 0: objs 1, 2; im 1: objs 1, 1, 2) with im 0 / inst 1 at visib_fract 0.05
    and im 1 / inst 0 with 30 visible pixels."""
    root = write_tiny_bop(tmp_path)

    def edit(d):
        d["0"][1]["visib_fract"] = 0.05
        d["1"][0]["px_count_visib"] = 30

    edit_json(scene_dir(root) / "scene_gt_info.json", edit)
    return root


def info(root: Path) -> dict:
    import json

    return json.loads((scene_dir(root) / "scene_gt_info.json").read_text())


def test_label_map():
    assert make_label_map([8, 2, 5, 2]) == {2: 1, 5: 2, 8: 3}


def test_targets_equal_files_and_thresholds(root: Path):
    ds = DetectionDataset(BopDataset(root, "tiny"), SPLIT, min_visib_fract=0.1, min_area_px=50)
    assert len(ds) == 2 and ds.label_map == {1: 1, 2: 2}
    infos = info(root)
    kept = {0: [0], 1: [1, 2]}  # gt indices surviving: visib 0.05 and 30 px dropped
    assert ds.num_instances() == 3
    for i in range(len(ds)):
        s = ds[i]
        assert s.image.dtype == torch.float32 and s.image.shape == (3, 480, 640)
        assert 0.0 <= float(s.image.min()) and float(s.image.max()) <= 1.0
        rgb = cv2.imread(str(scene_dir(root) / "rgb" / f"{s.im_id:06d}.png"))[:, :, ::-1]
        assert torch.allclose(s.image * 255, torch.from_numpy(rgb.copy()).permute(2, 0, 1).float(), atol=1e-3)
        ks = kept[s.im_id]
        expected_boxes = [[x, y, x + w, y + h] for x, y, w, h in (infos[str(s.im_id)][k]["bbox_visib"] for k in ks)]
        assert s.boxes.dtype == torch.float32 and s.boxes.tolist() == expected_boxes
        assert s.obj_ids.tolist() == [GT[s.im_id][k][0] for k in ks]
        assert s.labels.dtype == torch.int64 and s.labels.tolist() == s.obj_ids.tolist()  # label map {1: 1, 2: 2}
        assert s.masks.dtype == torch.uint8 and s.masks.shape == (len(ks), 480, 640)
        for j, k in enumerate(ks):
            m = cv2.imread(str(scene_dir(root) / "mask_visib" / f"{s.im_id:06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE)
            assert torch.equal(s.masks[j], torch.from_numpy((m > 127).astype(np.uint8)))
    loose = DetectionDataset(BopDataset(root, "tiny"), SPLIT, min_visib_fract=0.0, min_area_px=0)
    assert loose.num_instances() == 5


def test_empty_image_and_object_subset(root: Path):
    ds = DetectionDataset(BopDataset(root, "tiny"), SPLIT, label_map={2: 1})
    assert ds.obj_ids == [2]
    s0 = ds[0]  # its obj 2 instance has visib_fract 0.05: nothing left
    assert s0.boxes.shape == (0, 4) and s0.labels.shape == (0,) and s0.masks.shape == (0, 480, 640)
    assert s0.labels.dtype == torch.int64 and s0.boxes.dtype == torch.float32
    assert ds[1].labels.tolist() == [1]
    with pytest.raises(ValueError, match="background"):
        DetectionDataset(BopDataset(root, "tiny"), SPLIT, label_map={1: 0, 2: 1})
    with pytest.raises(ValueError, match="no label"):
        DetectionDataset(BopDataset(root, "tiny"), SPLIT, label_map={1: 1}, obj_ids=[1, 2])
    with pytest.raises(BopFormatError, match=r"obj_id"):
        DetectionDataset(BopDataset(root, "tiny"), SPLIT, label_map={1: 1, 7: 2})


def test_collate_feeds_torchvision(root: Path):
    from torchvision.models.detection.transform import GeneralizedRCNNTransform

    ds = DetectionDataset(BopDataset(root, "tiny"), SPLIT)
    loader = torch.utils.data.DataLoader(ds, batch_size=2, collate_fn=collate_detections)
    b = next(iter(loader))
    assert isinstance(b, DetectionBatch) and len(b) == 2 and b.im_ids == [0, 1]
    assert set(b.targets[0]) == {"boxes", "labels", "masks"}
    b = b.to("cpu")
    tr = GeneralizedRCNNTransform(min_size=240, max_size=320, image_mean=[0.5] * 3, image_std=[0.25] * 3)
    images, targets = tr(b.images, b.targets)
    assert images.tensors.shape == (2, 3, 256, 320)  # 240x320, padded to a multiple of 32
    np.testing.assert_allclose(targets[1]["boxes"].numpy(), b.targets[1]["boxes"].numpy() / 2, atol=1e-4)


def test_augmentation_keeps_objects(root: Path):
    aug = StrongAugmentation(AugmentationConfig(p_background=1.0, p_photometric=0.0), BackgroundPool(seed=0))
    plain = DetectionDataset(BopDataset(root, "tiny"), SPLIT)[0]
    augd = DetectionDataset(BopDataset(root, "tiny"), SPLIT, augmentation=aug)[0]
    union = np.zeros((480, 640), bool)
    for k in range(2):  # all instances, also the one dropped from the target
        union |= cv2.imread(str(scene_dir(root) / "mask_visib" / f"000000_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
    keep = torch.from_numpy(union)[None].expand(3, -1, -1)
    assert torch.equal(plain.image[keep], augd.image[keep])
    assert (plain.image[~keep] != augd.image[~keep]).float().mean() > 0.5
    assert torch.equal(plain.boxes, augd.boxes) and torch.equal(plain.masks, augd.masks)


def test_split_and_missing_file(root: Path):
    ds = DetectionDataset(BopDataset(root, "tiny"), SPLIT)
    train, val = split_train_val(ds, n_val_images=1, seed=0)
    assert len(train) == len(val) == 1 and set(train.image_keys()).isdisjoint(val.image_keys())
    assert {train[0].im_id, val[0].im_id} == {0, 1}
    (scene_dir(root) / "mask_visib" / "000001_000002.png").unlink()
    with pytest.raises(BopFormatError, match=r"000001_000002\.png.*not found"):
        ds[1]

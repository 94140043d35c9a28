"""PoseDataset on a tiny generated BOP dataset: instance counts from scene_gt_info, poses and masks
equal to the files, the by-image train/val split, batches, and errors that name the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.config import load_config, packaged_config
from cosy_lite.data.augmentation import AugmentationConfig, StrongAugmentation
from cosy_lite.data.backgrounds import BackgroundPool
from cosy_lite.data.pose_dataset import PoseDataset, collate_poses, split_train_val
from cosy_lite.errors import BopFormatError
from cosy_lite.structures import PoseBatch
from cosy_lite.synth.generator import SynthConfig, generate

CONFIG = packaged_config("synth", "tiny.yaml")
SMALL = ["train.n_images=6", "train.views_per_layout=6", "test.n_images=1", "test.views_per_layout=1"]  # one layout each
SPLIT = "train_pbr"


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pose_ds") / "tiny"
    generate(load_config(SynthConfig, CONFIG, SMALL), root, progress=False)
    return root


def scene_files(root: Path, split: str = SPLIT) -> tuple[dict, dict, dict]:
    d = root / split / "000000"
    return tuple(json.loads((d / f).read_text()) for f in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"))


@pytest.mark.parametrize("min_visib, min_px", [(0.1, 0), (0.5, 0), (0.0, 2000)])
def test_instance_count_matches_gt_info(root: Path, min_visib: float, min_px: int):
    _, infos, _ = scene_files(root)
    expected = sum(1 for v in infos.values() for e in v if e["visib_fract"] >= min_visib and e["px_count_visib"] >= min_px)
    assert 0 < expected < 24  # the threshold drops some of the 24 instances
    ds = PoseDataset(BopDataset(root, "tiny"), SPLIT, min_visib_fract=min_visib, min_px=min_px)
    assert len(ds) == expected
    assert len(ds.table) == sum(len(v) for v in infos.values()) == 24  # 6 images x 4 objects
    assert sum(ds.instance_counts().values()) == expected


def test_items_equal_files(root: Path):
    gts, infos, cams = scene_files(root)
    ds = PoseDataset(BopDataset(root, "tiny"), SPLIT, min_visib_fract=0.1, min_px=0)
    seen = set()
    for i in range(len(ds)):
        s = ds[i]
        seen.add((s.im_id, s.gt_idx))
        g, info, cam = gts[str(s.im_id)][s.gt_idx], infos[str(s.im_id)][s.gt_idx], cams[str(s.im_id)]
        assert s.scene_id == 0 and s.obj_id == g["obj_id"]
        assert s.TCO.dtype == torch.float32 and s.TCO.shape == (4, 4)
        np.testing.assert_allclose(s.TCO[:3, :3].numpy(), np.reshape(g["cam_R_m2c"], (3, 3)), atol=1e-6)
        np.testing.assert_allclose(s.TCO[:3, 3].numpy(), np.array(g["cam_t_m2c"]) / 1000.0, atol=1e-6)  # mm -> m
        np.testing.assert_array_equal(s.TCO[3].numpy(), [0, 0, 0, 1])
        np.testing.assert_allclose(s.K.numpy(), np.reshape(cam["cam_K"], (3, 3)), rtol=1e-6)
        x, y, w, h = info["bbox_visib"]
        assert s.bbox_visib.tolist() == [x, y, x + w, y + h]
        assert s.visib_fract == pytest.approx(info["visib_fract"], abs=1e-6)
        sd = root / SPLIT / "000000"
        visib = cv2.imread(str(sd / "mask_visib" / f"{s.im_id:06d}_{s.gt_idx:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        assert s.mask.dtype == torch.bool and torch.equal(s.mask, torch.from_numpy(visib))
        assert int(s.mask.sum()) == info["px_count_visib"]
        union = np.zeros_like(visib)
        for k in range(len(gts[str(s.im_id)])):
            union |= cv2.imread(str(sd / "mask_visib" / f"{s.im_id:06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        assert torch.equal(s.mask_any, torch.from_numpy(union))
        rgb = cv2.imread(str(sd / "rgb" / f"{s.im_id:06d}.jpg"))[:, :, ::-1]
        assert s.rgb.dtype == torch.uint8 and torch.equal(s.rgb, torch.from_numpy(rgb.copy()).permute(2, 0, 1))
    assert len(seen) == len(ds)


def test_obj_ids_filter_and_unknown_id(root: Path):
    bop = BopDataset(root, "tiny")
    ds = PoseDataset(bop, SPLIT, obj_ids=[2, 8], min_visib_fract=0.0, min_px=0)
    assert set(ds.instance_counts()) == {2, 8} and len(ds) == 12  # every object once per image
    assert {ds[i].obj_id for i in range(len(ds))} == {2, 8}
    with pytest.raises(BopFormatError, match=r"models_info.json.*\[obj_id\].*\[3\]"):
        PoseDataset(bop, SPLIT, obj_ids=[2, 3])


def test_split_train_val_by_image(root: Path):
    ds = PoseDataset(BopDataset(root, "tiny"), SPLIT, min_visib_fract=0.0, min_px=0)
    train, val = split_train_val(ds, n_val_images=2, seed=0)
    tr_imgs, va_imgs = set(train.image_keys()), set(val.image_keys())
    assert len(va_imgs) == 2 and len(tr_imgs) == 4 and not tr_imgs & va_imgs
    assert len(train) + len(val) == len(ds) == 24
    assert {(val[i].scene_id, val[i].im_id) for i in range(len(val))} == va_imgs
    again, _ = split_train_val(ds, n_val_images=2, seed=0)
    assert set(again.image_keys()) == tr_imgs
    _, val_f = split_train_val(ds, val_fraction=0.34, seed=1)
    assert len(val_f.image_keys()) == 2  # round(0.34 * 6)
    with pytest.raises(ValueError, match="exactly one"):
        split_train_val(ds)
    with pytest.raises(ValueError, match="cannot hold out"):
        split_train_val(ds, n_val_images=6)


def test_collate_and_dataloader(root: Path):
    ds = PoseDataset(BopDataset(root, "tiny"), SPLIT)
    loader = torch.utils.data.DataLoader(ds, batch_size=3, shuffle=False, collate_fn=collate_poses)
    b = next(iter(loader))
    assert isinstance(b, PoseBatch) and len(b) == 3
    assert b.rgb.shape == (3, 3, 480, 640) and b.rgb.dtype == torch.uint8
    assert b.K.shape == (3, 3, 3) and b.TCO.shape == (3, 4, 4) and b.bboxes.shape == (3, 4)
    assert b.masks.shape == b.masks_any.shape == (3, 480, 640) and b.masks.dtype == torch.bool
    assert b.obj_ids.tolist() == [ds[i].obj_id for i in range(3)]
    assert bool((b.masks <= b.masks_any).all())  # the instance lies inside the union
    moved = b.to("cpu")
    assert isinstance(moved, PoseBatch) and torch.equal(moved.TCO, b.TCO)


def test_augmentation_in_dataset_keeps_object_pixels(root: Path):
    aug = StrongAugmentation(AugmentationConfig(p_background=1.0, p_photometric=0.0), BackgroundPool(seed=0))
    plain = PoseDataset(BopDataset(root, "tiny"), SPLIT)
    augd = PoseDataset(BopDataset(root, "tiny"), SPLIT, augmentation=aug)
    a, b = plain[0], augd[0]
    keep = a.mask_any[None].expand_as(a.rgb)
    assert b.rgb.dtype == torch.uint8
    assert torch.equal(a.rgb[keep], b.rgb[keep]) and (a.rgb[~keep] != b.rgb[~keep]).float().mean() > 0.5


def test_missing_files_are_named(tmp_path: Path):
    from bop_fixtures import scene_dir, write_tiny_bop

    root = write_tiny_bop(tmp_path)
    ds = PoseDataset(BopDataset(root, "tiny"), "test", min_px=0)
    assert len(ds) == 5 and ds[0].obj_id == 1
    (scene_dir(root) / "mask_visib" / "000000_000001.png").unlink()
    with pytest.raises(BopFormatError, match=r"000000_000001\.png.*not found"):
        ds[0]  # the union needs every mask of the image
    (scene_dir(root) / "rgb" / "000001.png").unlink()
    with pytest.raises(BopFormatError, match=r"rgb/000001\.(png|jpg).*not found"):
        ds[3]
    shutil.move(scene_dir(root) / "scene_gt_info.json", tmp_path / "x.json")
    with pytest.raises(BopFormatError, match="scene_gt_info.json"):
        PoseDataset(BopDataset(root, "tiny"), "test")


def test_cached_items_equal_file_items(root: Path):
    files = PoseDataset(BopDataset(root, "tiny"), SPLIT, min_visib_fract=0.1, min_px=0)
    cached = PoseDataset(BopDataset(root, "tiny"), SPLIT, min_visib_fract=0.1, min_px=0)
    train, _ = split_train_val(cached, n_val_images=1, seed=0)
    train.cache_images(progress=False)
    assert train.cache is not None and train.cache.rgb.dtype == np.uint8
    n_mask_px_differ = 0
    for i in range(len(train)):
        a = train[i]
        b = files[int(np.nonzero(files.index == train.index[i])[0][0])]
        assert (a.im_id, a.gt_idx) == (b.im_id, b.gt_idx)
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.mask_any, b.mask_any) and torch.equal(a.TCO, b.TCO)
        n_mask_px_differ += int((a.mask != b.mask).sum())  # only where visible masks overlap (15 mm tolerance)
        assert int((a.mask & ~b.mask).sum()) == 0
    assert n_mask_px_differ <= 0.01 * sum(int(train[i].mask.sum()) for i in range(len(train)))

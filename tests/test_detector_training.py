"""Detector training task: a few steps through the real loop lower the loss, the checkpoint carries
the label map and reloads, bad checkpoints get clear errors, augmentation keeps every GT instance."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from cosy_lite.bop import io
from cosy_lite.config import load_config
from cosy_lite.nets.detector import Detector, detect
from cosy_lite.train.detector_task import DetectorTask, DetectorTrainConfig
from cosy_lite.train.loop import train
from cosy_lite.weights.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint
from cosy_lite.weights.loaders import load_detector

# 640x480 images scaled to 96x128, narrow heads, few proposals: a step takes ~0.1 s.
SMALL = ["detector.name=maskrcnn_resnet18_fpn", "detector.fpn_channels=32", "detector.mask_head_channels=32",
         "detector.box_head_size=128", "detector.min_size=96", "detector.max_size=128",
         "detector.anchor_sizes=[8,16,32,64,128]", "detector.rpn_pre_nms_top_n_train=200",
         "detector.rpn_post_nms_top_n_train=50", "detector.rpn_pre_nms_top_n_test=100",
         "detector.rpn_post_nms_top_n_test=20", "detector.box_batch_size_per_image=32",
         "data.val_images=1", "data.min_area_px=20", "loop.batch_size=2", "loop.num_workers=0", "loop.device=cpu",
         "loop.log_every=1", "loop.checkpoint_every=100", "loop.val_every=0", "optim.warmup_steps=1",
         "optim.lr=1e-3"]


def _task(root, extra=()) -> tuple[DetectorTrainConfig, DetectorTask]:
    cfg = load_config(DetectorTrainConfig, None, [*SMALL, "model=detector", "dataset=tiny", *extra])
    return cfg, DetectorTask(cfg, root)


def _train(root, out, steps: int, extra=()):
    cfg, task = _task(root, [f"loop.steps={steps}", *extra])
    return task, train(task, cfg.loop, cfg.optim, out, config=dataclasses.asdict(cfg), progress=False)


def test_held_out_images_and_masks_any(tiny_synth_root):
    _, task = _task(tiny_synth_root)
    ds = task.train_dataset()
    assert len(ds) == 5 and len(task.val_keys) == 1 and not set(task.val_keys) & set(ds.image_keys())
    assert task.label_map.obj_ids == (1, 2, 5, 8)
    for i in range(len(ds)):
        sample, mask_any = ds[i]
        rec = task.dataset.image("train_pbr", sample.scene_id, sample.im_id)
        union = np.zeros(mask_any.shape, dtype=bool)
        for k in range(len(rec.gt)):
            union |= io.load_mask(task.dataset.mask_path("train_pbr", rec.scene_id, rec.im_id, k, visib=True))
        assert np.array_equal(mask_any.numpy(), union)  # every GT instance, not only the targets
        assert bool((sample.masks.bool() <= mask_any).all())


def test_augmented_losses_repeat_under_the_loop_seeding(tiny_synth_root):
    _, task = _task(tiny_synth_root, ["augmentation.p_photometric=1.0", "augmentation.p_background=1.0"])
    ds = task.train_dataset()
    batch = task.collate([ds[0], ds[1]])
    torch.manual_seed(0)
    model = task.build_model().train()
    cpu = torch.device("cpu")
    runs = []
    for _ in range(2):
        torch.manual_seed(7)  # what the loop does before each step
        runs.append({k: float(v.detach()) for k, v in task.compute_losses(model, batch, 0, cpu).items()})
    assert runs[0] == runs[1]
    assert set(runs[0]) == {"total", "loss_classifier", "loss_box_reg", "loss_mask", "loss_objectness", "loss_rpn_box_reg"}
    assert runs[0]["total"] == pytest.approx(sum(v for k, v in runs[0].items() if k != "total"), rel=1e-5)


def test_few_steps_through_the_loop_lower_the_loss_and_checkpoint_reloads(tiny_synth_root, tmp_path):
    task, summary = _train(tiny_synth_root, tmp_path, steps=12, extra=["augmentation.enabled=false"])
    assert summary.steps_done == 12
    losses = [r["loss/total"] for r in map(json.loads, (tmp_path / "log.jsonl").read_text().splitlines())
              if r["type"] == "train"]
    assert len(losses) == 12 and all(np.isfinite(losses))
    assert np.mean(losses[-3:]) < 0.7 * losses[0], losses

    ckpt = load_checkpoint(tmp_path / "checkpoint.pt", kind="detector")
    assert ckpt.meta["label_map"] == {"obj_ids": [1, 2, 5, 8]} and ckpt.meta["dataset"] == "tiny"
    assert ckpt.meta["detector_config"]["min_size"] == 96 and ckpt.config["loop"]["steps"] == 12
    detector = load_detector(tmp_path / "checkpoint.pt")
    assert isinstance(detector, Detector) and not detector.training and detector.label_map.obj_ids == (1, 2, 5, 8)
    for k, v in detector.state_dict().items():
        torch.testing.assert_close(v, ckpt.model[k], rtol=0, atol=0)

    sample, _ = task.train_dataset()[0]
    (dets,) = detect(detector, [sample.image])
    assert dets.masks.shape[1:] == sample.image.shape[1:]
    assert set(dets.obj_ids.tolist()) <= {1, 2, 5, 8}
    val = task.validate(detector, torch.device("cpu"))
    assert set(val) == {"ap", "ap50", "ap75", "mask_ap", "mask_ap50"}
    assert all(np.isnan(v) or 0.0 <= v <= 1.0 for v in val.values())


def test_bad_checkpoints_name_the_file_and_the_problem(tmp_path):
    torch.manual_seed(0)
    cfg = load_config(DetectorTrainConfig, None, SMALL)
    from cosy_lite.nets.detector import LabelMap

    det = Detector(LabelMap((1, 2)), cfg.detector)
    good = Checkpoint(kind="detector", model=det.state_dict(), config={}, step=1, meta=det.meta())
    save_checkpoint(tmp_path / "good.pt", good)
    assert load_detector(tmp_path / "good.pt").label_map.obj_ids == (1, 2)

    (tmp_path / "cut.pt").write_bytes((tmp_path / "good.pt").read_bytes()[:1000])
    with pytest.raises(CheckpointError, match=r"cut\.pt: not a readable checkpoint"):
        load_detector(tmp_path / "cut.pt")
    save_checkpoint(tmp_path / "pose.pt", dataclasses.replace(good, kind="refiner"))
    with pytest.raises(CheckpointError, match=r"pose\.pt: field 'kind' is 'refiner'"):
        load_detector(tmp_path / "pose.pt")
    save_checkpoint(tmp_path / "nomap.pt", dataclasses.replace(good, meta={"detector_config": det.meta()["detector_config"]}))
    with pytest.raises(CheckpointError, match=r"nomap\.pt: field 'meta' lacks \['label_map'\]"):
        load_detector(tmp_path / "nomap.pt")
    other = dataclasses.replace(good, meta={**det.meta(), "label_map": {"obj_ids": [1, 2, 3]}})
    save_checkpoint(tmp_path / "other.pt", other)
    with pytest.raises(CheckpointError, match=r"other\.pt: field 'model' does not fit"):
        load_detector(tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not found"):
        load_detector(tmp_path / "missing.pt")

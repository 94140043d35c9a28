"""The BOP 2024/2025 6D detection task end to end on the tiny synthetic dataset: the generator's
``test_targets_bop24.json``, ``infer.py --task 6d-detection`` (every detection, no inst_count limit,
at most 100 per image) and ``cosy-lite eval --task 6d-detection`` on its output."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest
import torch
from test_inference import _detections_json, _save_pose_ckpt

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.detections import Detections
from cosy_lite.bop.results import read_results_csv
from cosy_lite.inference.bop_run import run_on_split, select_top_detections
from cosy_lite.inference.predictor import Predictor
from cosy_lite.inference.settings import InferenceConfig
from cosy_lite.inference.vivo import targets_by_image


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ckpts6d")
    return {"coarse": _save_pose_ckpt(d / "coarse.pt", "coarse"), "refiner": _save_pose_ckpt(d / "refiner.pt", "refiner")}


def test_generator_writes_the_bop24_targets(tiny_synth_root):
    bop24 = json.loads((tiny_synth_root / "test_targets_bop24.json").read_text())
    ds = BopDataset(tiny_synth_root)
    images = sorted(targets_by_image(ds.test_targets()))
    assert bop24 == [{"im_id": i, "scene_id": s} for s, i in images]  # the toolkit's keys, nothing else
    assert [(t.scene_id, t.im_id) for t in ds.test_image_targets()] == images


def test_select_top_detections():
    det = Detections(torch.zeros(5, 4), torch.tensor([1, 9, 2, 1, 2]), torch.tensor([0.2, 0.99, 0.8, 0.8, 0.1]))
    out = select_top_detections(det, {1, 2}, n=3)
    assert out.obj_ids.tolist() == [2, 1, 1] and out.scores.tolist() == pytest.approx([0.8, 0.8, 0.2])


def test_6d_detection_keeps_every_detection(tiny_synth_root, ckpts, tmp_path):
    ds = BopDataset(tiny_synth_root)
    scores = _detections_json(tmp_path / "dets.json", ds, n_copies=3, time_s=0.1)
    p = Predictor.from_checkpoints(coarse=ckpts["coarse"], refiner=ckpts["refiner"], dataset=tiny_synth_root,
                                   config=InferenceConfig(n_refiner_iterations=1))
    summary = run_on_split(p, ds, tmp_path, detections=tmp_path / "dets.json", progress=False, task="6d-detection")
    assert summary.ok and summary.n_invalid == 0
    got = Counter((e.scene_id, e.im_id, e.obj_id) for e in read_results_csv(summary.csv_path))
    # every GT instance's 3 detections, also of instances under 10 % visible (no inst_count limit)
    assert got == Counter({k: len(v) for k, v in scores.items()})
    assert sum(got.values()) > sum(t.inst_count for t in ds.test_targets())


def test_infer_and_eval_commands(tiny_synth_root, ckpts, tmp_path, monkeypatch):
    import infer
    from cosy_lite.cli import main as cli

    rc = infer.main(["--dataset", str(tiny_synth_root), "--coarse", str(ckpts["coarse"]), "--refiner",
                     str(ckpts["refiner"]), "--n-refiner-iters", "1", "--detections", "oracle", "--out",
                     str(tmp_path), "--task", "6d-detection", "--no-progress"])
    assert rc == 0
    csv = tmp_path / "cosylite_tiny-test.csv"
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert cli(["eval", "--dataset", str(tiny_synth_root), "--results", str(csv), "--task", "6d-detection",
                "--no-progress"]) == 0
    # without --out: a results folder of the current directory, nothing beside the CSV
    scores = json.loads((tmp_path / "elsewhere" / "outputs" / "eval" / csv.stem / "scores_bop24.json").read_text())
    assert not (tmp_path / f"{csv.stem}_eval").exists()
    assert 0.0 <= scores["bop24_mAP"] <= 1.0
    assert scores["bop24_mAP"] == pytest.approx((scores["bop24_mAP_mssd"] + scores["bop24_mAP_mspd"]) / 2)
    assert scores["bop25_mAP"] == scores["bop24_mAP_mssd"]

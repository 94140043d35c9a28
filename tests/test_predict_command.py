"""``cosy-lite predict`` on one generated image with tiny untrained checkpoints (torch) and their ONNX
export: JSON (R, t in mm, the BOP19 row), CSV, overlay, timings; clear errors for bad inputs.

Untrained pose nets output a zero update, so every pose is the starting pose of its box (canonical
rotation, depth from the box): the expected poses are computed independently from the boxes.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_inference import OBJ_IDS, _save_pose_ckpt  # the tiny checkpoints of the inference tests

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.results import read_results_csv
from cosy_lite.cli import main as cli
from cosy_lite.nets.initial_pose import CANONICAL_ROTATIONS, initial_pose_from_boxes


@pytest.fixture(scope="module")
def setup(tiny_synth_root, tmp_path_factory) -> dict:
    """Checkpoints, an export folder, one test image with its camera file and GT-box detections."""
    from cosy_lite.export.onnx_export import export_models
    from cosy_lite.nets.detector import Detector, DetectorConfig, LabelMap
    from cosy_lite.weights.checkpoint import Checkpoint, save_checkpoint

    d = tmp_path_factory.mktemp("predict")
    torch.manual_seed(0)
    det = Detector(LabelMap(tuple(OBJ_IDS)), DetectorConfig(
        name="maskrcnn_mobilenet_v3_large_fpn", fpn_channels=32, mask_head_channels=16, box_head_size=64,
        min_size=160, max_size=214, rpn_pre_nms_top_n_test=100, rpn_post_nms_top_n_test=50,
        box_score_thresh=0.0, box_detections_per_img=5))
    save_checkpoint(d / "detector.pt", Checkpoint("detector", det.state_dict(), {}, 0, meta=det.meta()))
    coarse, refiner = _save_pose_ckpt(d / "coarse.pt", "coarse"), _save_pose_ckpt(d / "refiner.pt", "refiner")
    export_models(d / "export", coarse=coarse, refiner=refiner)
    ds = BopDataset(tiny_synth_root)
    rec = next(ds.images("test"))
    (d / "camera.json").write_text(json.dumps({"cam_K": rec.camera.K.reshape(-1).tolist(),
                                               "depth_scale": rec.camera.depth_scale}))
    visible = [(g, i) for g, i in zip(rec.gt, rec.gt_info) if i.visib_fract >= 0.1]
    dets = [{"scene_id": rec.scene_id, "image_id": rec.im_id, "category_id": g.obj_id, "score": 0.9 - 0.1 * k,
             "bbox": [float(v) for v in i.bbox_visib], "time": 0.0} for k, (g, i) in enumerate(visible)]
    (d / "dets.json").write_text(json.dumps(dets))
    return {"dir": d, "coarse": coarse, "refiner": refiner, "detector": d / "detector.pt", "export": d / "export",
            "rec": rec, "root": tiny_synth_root, "dets": dets}


def _args(s: dict, out: Path, *extra: str) -> list[str]:
    return ["predict", "--rgb", str(s["rec"].rgb_path), "--camera", str(s["dir"] / "camera.json"),
            "--meshes", str(s["root"]), "--out", str(out), "--n-refiner-iters", "1", *extra]


def _expected_poses(s: dict) -> dict[int, np.ndarray]:
    """obj_id -> starting pose [4,4] (m) of its GT box (each object is once in the detections)."""
    K = torch.as_tensor(s["rec"].camera.K)
    ds = BopDataset(s["root"])
    out = {}
    for d in s["dets"]:
        x, y, w, h = d["bbox"]
        box = torch.tensor([[x, y, x + w, y + h]], dtype=torch.float64)
        diam = torch.tensor([ds.models_info[d["category_id"]].diameter], dtype=torch.float64)
        out.setdefault(d["category_id"], []).append(initial_pose_from_boxes(box, K[None], diam)[0].numpy())
    return out


def _check_outputs(s: dict, out: Path, backend: str) -> dict:
    pred = json.loads((out / "predictions.json").read_text())
    assert pred["backend"] == backend and len(pred["estimates"]) == len(s["dets"])
    expected = _expected_poses(s)
    rows = (out / "predictions.csv").read_text().split("\n")
    assert rows[0] == "scene_id,im_id,obj_id,score,R,t,time"
    for e, row in zip(pred["estimates"], rows[1:]):
        t_m = np.array(e["t"]) / 1000.0  # t is in millimetres
        assert min(np.abs(t_m - T[:3, 3]).max() for T in expected[e["obj_id"]]) < 1e-5
        np.testing.assert_allclose(e["R"], CANONICAL_ROTATIONS["z_up"].numpy(), atol=1e-6)
        assert e["bop19_csv_row"] == row and row.startswith(f"0,0,{e['obj_id']},")
    assert [e["score"] for e in pred["estimates"]] == pytest.approx(sorted((d["score"] for d in s["dets"]), reverse=True))
    for e in pred["estimates"]:  # the detection and the start of each estimate
        d = e["detection"]
        assert d["score"] == e["score"] and d["mask_rle"] is None  # (given as boxes)
        x1, y1, x2, y2 = d["box_xyxy_px"]
        assert any(np.allclose([x1, y1, x2 - x1, y2 - y1], g["bbox"], atol=1e-3) for g in s["dets"])
        start = np.array(e["start"]["t"]) / 1000.0  # the box pose the coarse net started from
        assert min(np.abs(start - T[:3, 3]).max() for T in expected[e["obj_id"]]) < 1e-5
    assert set(pred["timings_ms"]) == {"detection", "crops", "render", "networks", "icp", "total", "templates"}
    stages = sum(v for k, v in pred["timings_ms"].items() if k not in ("total", "templates"))
    assert stages <= pred["timings_ms"]["total"] * 1.001  # the stages add up within the image's total
    assert pred["timings_ms"]["networks"] > 0 and pred["seconds"] > 0
    assert cv2.imread(str(out / "overlay.png")).shape == (480, 640, 3)
    est = read_results_csv(out / "predictions.csv")
    assert len(est) == len(s["dets"]) and len({e.time for e in est}) == 1
    return pred


def test_torch_backend_with_given_detections(setup, tmp_path):
    assert cli(_args(setup, tmp_path, "--coarse", str(setup["coarse"]), "--refiner", str(setup["refiner"]),
                     "--detections", str(setup["dir"] / "dets.json"))) == 0
    _check_outputs(setup, tmp_path, "torch")


def test_onnx_backend_gives_the_same_poses(setup, tmp_path):
    assert cli(_args(setup, tmp_path, "--onnx", str(setup["export"]), "--detections", str(setup["dir"] / "dets.json"))) == 0
    _check_outputs(setup, tmp_path, "onnx")


def test_detector_icp_and_an_object_subset(setup, tmp_path):
    rec = setup["rec"]
    assert cli(_args(setup, tmp_path, "--coarse", str(setup["coarse"]), "--detector", str(setup["detector"]),
                     "--depth", str(rec.depth_path), "--icp", "--objects", "1,5")) == 0
    pred = json.loads((tmp_path / "predictions.json").read_text())
    assert pred["icp"] and len(pred["estimates"]) <= 5  # the tiny detector keeps 5 boxes
    assert {e["obj_id"] for e in pred["estimates"]} <= {1, 5}


def test_templates_start_without_a_coarse_checkpoint(setup, tmp_path, capsys):
    """--start templates --refiner CKPT: the detector's masks matched to silhouette templates."""
    # the toy detector scores below predict's default threshold (0.5): every detection, the best per object
    assert cli(_args(setup, tmp_path, "--start", "templates", "--candidates", "1", "--refiner", str(setup["refiner"]),
                     "--detector", str(setup["detector"]), "--templates-cache", str(tmp_path / "tc"),
                     "--min-score", "0")) == 0
    pred = json.loads((tmp_path / "predictions.json").read_text())
    assert 0 < len(pred["estimates"]) <= 5
    # the templates were rendered in this run: a one-time cost, apart from the image's total (it was in it, twice)
    ms = pred["timings_ms"]
    assert ms["templates"] > 0 and sum(v for k, v in ms.items() if k not in ("total", "templates")) <= ms["total"] * 1.001
    for e in pred["estimates"]:
        assert np.isfinite(e["t"]).all() and 100 < e["t"][2] < 5000  # mm, in front of the camera
        R = np.array(e["R"])
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
    from cosy_lite.bop.detections import rle_to_mask

    for e in pred["estimates"]:  # the detector's masks, recorded
        mask = rle_to_mask(e["detection"]["mask_rle"])
        assert mask.shape == (480, 640) and mask.any()
    # BOP22 detections without "segmentation" (it stopped: "these detections have none"): their boxes
    # stand in for the masks the templates need, with a warning
    with pytest.warns(RuntimeWarning, match="boxes only: the boxes stand in for their masks"):
        assert cli(_args(setup, tmp_path / "boxes", "--start", "templates", "--refiner", str(setup["refiner"]),
                         "--detections", str(setup["dir"] / "dets.json"), "--templates-cache", str(tmp_path / "tc"))) == 0
    boxes_only = json.loads((tmp_path / "boxes" / "predictions.json").read_text())
    assert len(boxes_only["estimates"]) == len(setup["dets"])
    assert all(e["detection"]["mask_rle"] is None for e in boxes_only["estimates"])


def test_python_api(setup):
    from cosy_lite.bop import io
    from cosy_lite.inference.command_predict import predict_image
    from cosy_lite.inference.predictor import Predictor

    p = Predictor.from_checkpoints(coarse=setup["coarse"], models_dir=setup["root"] / "models",
                                   detector=setup["detector"])
    cam = io.load_camera_file(setup["dir"] / "camera.json")
    out = predict_image(p, io.load_image(setup["rec"].rgb_path), cam.K)
    assert out.overlay.shape == (480, 640, 3) and len(out.estimates) <= 5 and out.seconds > 0


@pytest.mark.parametrize("content, field, message", [
    ({"fx": 500.0, "cx": 320.0, "cy": 240.0}, "fy", "missing field"),
    ({"cam_K": [500.0, 0, 320, 0, 500, 240, 0, 0]}, "cam_K", "expected 9 numbers"),
    ({"K": [[-500.0, 0, 320], [0, 500, 240], [0, 0, 1]]}, "K", "focal lengths must be > 0"),
    ({"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0, "width": 1280, "height": 960}, "width", "1280x960"),
    ([1, 2, 3], "", "expected a JSON object"),
])
def test_bad_camera_files(setup, tmp_path, capsys, content, field, message):
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps(content))
    args = _args(setup, tmp_path / "out", "--coarse", str(setup["coarse"]), "--detector", str(setup["detector"]))
    args[args.index("--camera") + 1] = str(cam)
    assert cli(args) == 2
    err = capsys.readouterr().err
    assert str(cam) in err and message in err and (not field or f"[{field}]" in err)


def test_bad_arguments(setup, tmp_path, capsys):
    ck = ["--coarse", str(setup["coarse"]), "--detector", str(setup["detector"])]
    assert cli(_args(setup, tmp_path, *ck, "--icp")) == 2
    assert "--icp needs --depth" in capsys.readouterr().err
    assert cli(_args(setup, tmp_path, *ck, "--objects", "1,99")) == 2
    assert "[99]" in capsys.readouterr().err
    assert cli(_args(setup, tmp_path, "--coarse", str(setup["coarse"]))) == 2
    assert "no detections" in capsys.readouterr().err
    bad_models = _args(setup, tmp_path, *ck)
    bad_models[bad_models.index("--meshes") + 1] = str(setup["export"])
    assert cli(bad_models) == 2
    assert "pass it as --onnx" in capsys.readouterr().err
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 120), np.uint16))
    assert cli(_args(setup, tmp_path, *ck, "--depth", str(small))) == 2
    err = capsys.readouterr().err
    assert str(small) in err and "120x100" in err


def test_infer_writes_the_detectors_detections_for_the_2d_tasks(setup, tmp_path):
    """infer.py with the detector also writes every detection as BOP22 JSON beside the CSV (before
    the per-object selection), which cosy-lite eval --task 2d-detection / 2d-segmentation scores."""
    import infer
    from cosy_lite.bop.detections import read_bop22_entries
    from cosy_lite.eval.detection import COCO_KEYS

    out = tmp_path / "res"
    assert infer.main(["--dataset", str(setup["root"]), "--coarse", str(setup["coarse"]), "--detector",
                       str(setup["detector"]), "--n-refiner-iters", "0", "--limit-images", "2", "--no-progress",
                       "--threads", "1", "--out", str(out)]) == 0
    csv = next(out.glob("*.csv"))
    entries = read_bop22_entries(csv.with_suffix(".json"))
    rows = read_results_csv(csv)
    assert len({(e["scene_id"], e["image_id"]) for e in entries}) == 2  # both images
    assert len(entries) == 10 >= len(rows) > 0  # 5 per image (box_detections_per_img): all, not the selection
    assert all(e["segmentation"] is not None and e["time"] > 0 for e in entries)
    for task, name in (("2d-detection", "bbox"), ("2d-segmentation", "segm")):
        assert cli(["eval", "--dataset", str(setup["root"]), "--results", str(csv.with_suffix(".json")),
                    "--task", task, "--out", str(tmp_path / "ev")]) == 0
        scores = json.loads((tmp_path / "ev" / f"scores_bop22_coco_{name}.json").read_text())
        assert list(scores) == [*COCO_KEYS, "average_time_per_image"] and scores["average_time_per_image"] > 0
    # oracle detections are not the detector's: no JSON
    assert infer.main(["--dataset", str(setup["root"]), "--coarse", str(setup["coarse"]), "--detections", "oracle",
                       "--n-refiner-iters", "0", "--limit-images", "1", "--no-progress", "--out", str(tmp_path / "o")]) == 0
    assert not list((tmp_path / "o").glob("*.json"))

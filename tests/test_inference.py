"""Inference pipeline on the tiny synthetic dataset with freshly initialised small models: the
BOP19 CSV (header, ViVo top-n rows, one time per image, poses in mm), detection sources, empty
detections, invalid poses never written, clear errors for bad checkpoints."""

from __future__ import annotations

import copy
import json
import warnings
from collections import defaultdict
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.detections import Detections
from cosy_lite.bop.results import HEADER, read_results_csv
from cosy_lite.inference.bop_run import run_on_split
from cosy_lite.inference.predictor import TIMING_KEYS, Predictor
from cosy_lite.inference.settings import InferenceConfig
from cosy_lite.inference.vivo import most_confident, select_candidates, select_top_instances, targets_by_image
from cosy_lite.nets.initial_pose import CANONICAL_ROTATIONS, initial_pose_from_boxes
from cosy_lite.weights.checkpoint import Checkpoint, save_checkpoint
from cosy_lite.weights.loaders import PoseModel

OBJ_IDS = [1, 2, 5, 8]
CROP = [60, 80]


def _save_pose_ckpt(path: Path, kind: str, obj_ids=OBJ_IDS) -> Path:
    from cosy_lite.weights.pose_nets import PoseNetConfig, build_pose_net

    torch.manual_seed(0)
    cfg = PoseNetConfig(backbone="resnet18", crop_resolution=CROP)
    meta = {"obj_ids": list(obj_ids), "net": asdict(cfg), "dataset": "tiny", "model": kind}
    save_checkpoint(path, Checkpoint(kind, build_pose_net(cfg).state_dict(), {"net": asdict(cfg)}, 0, meta=meta))
    return path


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, Path]:
    """Untrained checkpoints: the pose nets' zero-initialised heads make every update the identity."""
    from cosy_lite.nets.detector import Detector, DetectorConfig, LabelMap

    d = tmp_path_factory.mktemp("ckpts")
    torch.manual_seed(0)
    det = Detector(LabelMap(tuple(OBJ_IDS)), DetectorConfig(
        name="maskrcnn_mobilenet_v3_large_fpn", fpn_channels=32, mask_head_channels=16, box_head_size=64,
        min_size=160, max_size=214, rpn_pre_nms_top_n_test=100, rpn_post_nms_top_n_test=50,
        box_score_thresh=0.0, box_detections_per_img=5))
    save_checkpoint(d / "detector.pt", Checkpoint("detector", det.state_dict(), {}, 0, meta=det.meta()))
    return {"coarse": _save_pose_ckpt(d / "coarse.pt", "coarse"),
            "refiner": _save_pose_ckpt(d / "refiner.pt", "refiner"), "detector": d / "detector.pt"}


@pytest.fixture(scope="module")
def predictor(tiny_synth_root, ckpts) -> Predictor:
    return Predictor.from_checkpoints(coarse=ckpts["coarse"], refiner=ckpts["refiner"], dataset=tiny_synth_root,
                                      config=InferenceConfig(n_refiner_iterations=1))


def _rows_by_image(csv: Path):
    rows = defaultdict(list)
    for e in read_results_csv(csv):
        rows[(e.scene_id, e.im_id)].append(e)
    return rows


def test_infer_oracle_writes_a_valid_bop19_csv(tiny_synth_root, ckpts, tmp_path):
    import cv2

    import infer
    from cosy_lite.cli import main as cli

    rc = infer.main(["--dataset", str(tiny_synth_root), "--coarse", str(ckpts["coarse"]), "--refiner",
                     str(ckpts["refiner"]), "--n-refiner-iters", "1", "--detections", "oracle", "--out",
                     str(tmp_path), "--method", "cosy_lite", "--vis", "1", "--no-progress"])
    assert rc == 0
    csv = tmp_path / "cosylite_tiny-test.csv"
    text = csv.read_text()
    assert text.split("\n")[0] == HEADER and not text.endswith("\n")
    ds = BopDataset(tiny_synth_root)
    targets = targets_by_image(ds.test_targets())
    rows = _rows_by_image(csv)
    assert set(rows) == set(targets)
    for key, counts in targets.items():
        est = rows[key]
        per_obj = defaultdict(int)
        for e in est:
            per_obj[e.obj_id] += 1
        assert dict(per_obj) == counts  # oracle: every target instance once
        assert len({e.time for e in est}) == 1 and est[0].time > 0
        # Untrained nets change nothing: each pose is the starting pose of its GT visible box (t in mm in the file).
        rec = ds.image("test", *key)
        boxes = torch.tensor([[b[0], b[1], b[0] + b[2], b[1] + b[3]] for b in (i.bbox_visib for i in rec.gt_info)],
                             dtype=torch.float64)
        diam = torch.tensor([ds.models_info[g.obj_id].diameter for g in rec.gt], dtype=torch.float64)
        starts = initial_pose_from_boxes(boxes, torch.as_tensor(rec.camera.K)[None].expand(len(boxes), 3, 3), diam)
        for e in est:
            assert np.isfinite(e.TCO).all() and 0.3 < e.TCO[2, 3] < 2.0
            d = [np.abs(e.TCO[:3, 3] - s[:3, 3].numpy()).max() for g, s in zip(rec.gt, starts) if g.obj_id == e.obj_id]
            assert min(d) < 1e-5  # m: 0.01 mm
            np.testing.assert_allclose(e.TCO[:3, :3], CANONICAL_ROTATIONS["z_up"].numpy(), atol=1e-6)
    lines = text.split("\n")[1:]
    t_mm = np.array([[float(v) for v in line.split(",")[5].split()] for line in lines])
    assert (np.linalg.norm(t_mm, axis=1) > 300).all()  # millimetres, not metres
    vis = sorted((tmp_path / "vis").glob("*.png"))
    assert len(vis) == 1 and cv2.imread(str(vis[0])).shape == (480, 640, 3)
    assert cli(["check-results", str(csv), "--dataset", str(tiny_synth_root)]) == 0


def test_infer_from_templates_needs_no_coarse_model(tiny_synth_root, ckpts, tmp_path, capsys):
    """--start templates: the GT masks (oracle) matched to templates; no refiner iteration, so each
    written pose is a template pose: in front of the camera, at about the GT depth."""
    import infer

    rc = infer.main(["--dataset", str(tiny_synth_root), "--start", "templates", "--refiner", str(ckpts["refiner"]),
                     "--n-refiner-iters", "0", "--detections", "oracle", "--out", str(tmp_path), "--no-progress",
                     "--templates-cache", str(tmp_path / "templates")])
    assert rc == 0, capsys.readouterr().err
    ds = BopDataset(tiny_synth_root)
    rows = _rows_by_image(tmp_path / "cosylite_tiny-test.csv")
    assert set(rows) == set(targets_by_image(ds.test_targets()))
    ratios = []
    for key, est in rows.items():
        gt = {g.obj_id: g.TCO for g in ds.image("test", *key).gt}
        ratios += [e.TCO[2, 3] / gt[e.obj_id][2, 3] for e in est]  # both in m (the reader converts)
    assert 0.8 < float(np.median(ratios)) < 1.25  # template depth from the visible box
    assert len(list((tmp_path / "templates").glob("*.npz"))) >= 1
    assert infer.main(["--dataset", str(tiny_synth_root), "--detections", "oracle", "--start", "templates"]) == 2
    assert "--refiner CKPT" in capsys.readouterr().err  # templates without a coarse model need a refiner


def test_icp_run_also_writes_its_poses_before_icp(tiny_synth_root, ckpts, tmp_path):
    """method_before_icp (infer.py --also-before-icp): the second CSV holds exactly what the same run
    without ICP writes; the first holds ICP's poses (an ICP that accepts any update, so that they differ)."""
    import infer
    from cosy_lite.inference.icp import IcpConfig

    ds = BopDataset(tiny_synth_root)
    kw = dict(coarse=ckpts["coarse"], refiner=ckpts["refiner"], dataset=ds)
    loose = IcpConfig(max_rotation_deg=180.0, max_translation=1.0, min_fitness=0.0, max_inlier_rmse=1.0)
    rgb_only = InferenceConfig(n_refiner_iterations=1)
    with_icp = InferenceConfig(n_refiner_iterations=1, icp=True, icp_settings=loose)
    run_on_split(Predictor.from_checkpoints(**kw, config=rgb_only), ds, tmp_path / "rgb", method="rgb", detections="oracle",
                 progress=False)
    s = run_on_split(Predictor.from_checkpoints(**kw, config=with_icp), ds, tmp_path / "both",
                     method="icp", detections="oracle", progress=False, method_before_icp="rgb")
    assert s.ok and s.icp_accepted > 0 and s.csv_before_icp == tmp_path / "both" / "rgb_tiny-test.csv"
    alone = read_results_csv(tmp_path / "rgb" / "rgb_tiny-test.csv")
    before = read_results_csv(s.csv_before_icp)
    after = read_results_csv(s.csv_path)
    assert len(alone) == len(before) == len(after) > 0
    for a, b, c in zip(alone, before, after):
        assert (a.scene_id, a.im_id, a.obj_id, a.score) == (b.scene_id, b.im_id, b.obj_id, b.score)
        np.testing.assert_allclose(b.TCO, a.TCO, atol=1e-6)  # mm-rounded CSV values
        assert b.time <= c.time
    assert sum(np.abs(b.TCO - c.TCO).max() > 1e-4 for b, c in zip(before, after)) >= s.icp_accepted // 2
    common = ["--dataset", str(tiny_synth_root), "--coarse", str(ckpts["coarse"]), "--detections", "oracle"]
    assert infer.main(common + ["--out", str(tmp_path), "--also-before-icp", "rgb"]) == 2  # needs --icp
    assert infer.main(common + ["--out", str(tmp_path), "--icp", "--also-before-icp", "cosylite"]) == 2  # same name


def _detections_json(path: Path, ds: BopDataset, n_copies: int, time_s: float) -> dict:
    """Per GT instance ``n_copies`` detections (box shifted by 2 px each, decreasing scores);
    returns {(scene, im, obj): scores}."""
    entries, scores = [], defaultdict(list)
    for scene_id, im_id in targets_by_image(ds.test_targets()):
        rec = ds.image("test", scene_id, im_id)
        for g, info in zip(rec.gt, rec.gt_info):
            for k in range(n_copies):
                s = round(0.9 - 0.1 * k - 0.001 * len(entries), 6)
                x, y, w, h = info.bbox_visib
                entries.append({"scene_id": scene_id, "image_id": im_id, "category_id": g.obj_id, "score": s,
                                "bbox": [x + 2 * k, y, w, h], "time": time_s})
                scores[(scene_id, im_id, g.obj_id)].append(s)
    path.write_text(json.dumps(entries))
    return scores


def test_vivo_keeps_the_top_inst_count_detections_per_object(tiny_synth_root, predictor, tmp_path):
    ds = BopDataset(tiny_synth_root)
    scores = _detections_json(tmp_path / "dets.json", ds, n_copies=3, time_s=0.25)
    summary = run_on_split(predictor, ds, tmp_path, detections=tmp_path / "dets.json", progress=False)
    assert summary.ok and summary.n_invalid == 0
    targets = targets_by_image(ds.test_targets())
    rows = _rows_by_image(summary.csv_path)
    for key, counts in targets.items():
        est = rows[key]
        got = defaultdict(list)
        for e in est:
            got[e.obj_id].append(e.score)
        assert set(got) == set(counts)
        for obj, n in counts.items():
            assert len(got[obj]) == n < len(scores[(*key, obj)])  # more detections than inst_count
            assert got[obj] == pytest.approx(sorted(scores[(*key, obj)], reverse=True)[:n], abs=1e-6)
        assert [e.score for e in est] == sorted((e.score for e in est), reverse=True)  # ranked by score
        assert len({e.time for e in est}) == 1 and est[0].time > 0.25  # the file's detection time counts


def test_a_score_threshold_comes_before_the_vivo_selection(tiny_synth_root, predictor, tmp_path):
    from cosy_lite.inference.detection_filter import DetectionFilter

    ds = BopDataset(tiny_synth_root)
    scores = _detections_json(tmp_path / "dets.json", ds, n_copies=3, time_s=0.25)
    threshold = sorted(s[0] for s in scores.values())[len(scores) // 2]  # half of the objects' best detections pass
    predictor.detection_filter = DetectionFilter(min_score=threshold)
    try:
        summary = run_on_split(predictor, ds, tmp_path, detections=tmp_path / "dets.json", progress=False)
        rgb_rec = next(ds.images("test"))
        det = Detections(torch.tensor([[10, 10, 40, 40], [100, 100, 130, 140]], dtype=torch.float32),
                         torch.tensor([1, 2]), torch.tensor([threshold - 0.01, threshold + 0.01]))
        est = predictor.predict(ds.load_rgb(rgb_rec), rgb_rec.camera.K, detections=det)
    finally:
        predictor.detection_filter = DetectionFilter()
    targets = targets_by_image(ds.test_targets())
    kept = {k for k, s in scores.items() if s[0] >= threshold and k[2] in targets[k[:2]]}
    rows = [(e.scene_id, e.im_id, e.obj_id) for es in _rows_by_image(summary.csv_path).values() for e in es]
    assert sorted(rows) == sorted(kept) and 0 < len(kept) < len(scores)
    assert est.obj_ids.tolist() == [2]


def test_select_top_instances():
    det = Detections(torch.tensor([[0, 0, 10, 10]] * 6, dtype=torch.float32), torch.tensor([1, 2, 1, 1, 2, 5]),
                     torch.tensor([0.2, 0.9, 0.8, 0.5, 0.3, 0.7]))
    out = select_top_instances(det, {1: 2, 2: 1})
    assert out.obj_ids.tolist() == [2, 1, 1] and out.scores.tolist() == pytest.approx([0.9, 0.8, 0.5])


def test_select_candidates_takes_more_per_instance_above_the_score_ratio():
    det = Detections(torch.tensor([[0, 0, 10, 10]] * 6, dtype=torch.float32), torch.tensor([1, 2, 1, 1, 2, 5]),
                     torch.tensor([0.2, 0.9, 0.8, 0.5, 0.3, 0.7]))
    one = select_candidates(det, {1: 1, 2: 1})
    assert one.scores.tolist() == select_top_instances(det, {1: 1, 2: 1}).scores.tolist()
    # obj 1: 0.8 and 0.5 (>= 0.5 x 0.8); obj 2: 0.9, its 0.3 under 0.45; obj 5: not a target
    out = select_candidates(det, {1: 1, 2: 1}, per_instance=2, score_ratio=0.5)
    assert out.obj_ids.tolist() == [2, 1, 1] and out.scores.tolist() == pytest.approx([0.9, 0.8, 0.5])
    # two instances of obj 1: its best two always, a third only above the ratio (0.2 < 0.4)
    two = select_candidates(det, {1: 2}, per_instance=2, score_ratio=0.5)
    assert two.scores.tolist() == pytest.approx([0.8, 0.5])
    assert len(select_candidates(det, {1: 2}, per_instance=2, score_ratio=0.0)) == 3
    with pytest.raises(ValueError, match="per_instance"):
        select_candidates(det, {1: 1}, per_instance=0)


def test_most_confident_keeps_each_objects_instances_of_highest_confidence():
    ids = torch.tensor([1, 1, 2, 2, 5, 1])
    conf = torch.tensor([0.2, 0.6, 0.9, 0.9, 0.8, 0.7], dtype=torch.float64)
    assert most_confident(ids, conf, {1: 1, 2: 1}).tolist() == [2, 5]  # (ties: the earlier; obj 5 not asked)
    assert most_confident(ids, conf, {1: 2, 2: 2, 5: 1}).tolist() == [1, 2, 3, 4, 5]


def test_empty_detections(tiny_synth_root, predictor, tmp_path):
    ds = BopDataset(tiny_synth_root)
    rec = next(ds.images("test"))
    est = predictor.predict(ds.load_rgb(rec), rec.camera.K, detections=Detections.empty())
    assert len(est) == 0 and est.TCO.shape == (0, 4, 4) and set(est.timings) == set(TIMING_KEYS)
    (tmp_path / "none.json").write_text("[]")
    summary = run_on_split(predictor, ds, tmp_path, detections=tmp_path / "none.json", progress=False)
    assert summary.ok and summary.n_estimates == 0 and summary.csv_path.read_text() == HEADER


def test_predict_from_models_dir_with_icp(tiny_synth_root, ckpts):
    from cosy_lite.bop.detections import oracle_detections

    ds = BopDataset(tiny_synth_root)
    p = Predictor.from_checkpoints(coarse=ckpts["coarse"], models_dir=tiny_synth_root / "models",
                                   config=InferenceConfig(icp=True))
    rec = next(ds.images("test"))
    det = oracle_detections(ds, rec, min_visib_fract=0.1)
    est = p.predict(ds.load_rgb(rec), rec.camera.K, ds.load_depth(rec), detections=det)
    assert len(est) == len(det) and len(est.icp) == len(det) and est.timings["icp"] > 0
    assert all(r.accepted or r.reason for r in est.icp) and bool(est.valid.all())
    assert all(est.timings[k] > 0 for k in ("crops", "render", "networks", "total")) and est.timings["detection"] == 0
    assert est.timings["total"] >= sum(est.timings[k] for k in ("crops", "render", "networks", "icp"))
    # before_icp(): the refiner's poses, as a predictor without ICP gives them; ICP's own results after
    plain = Predictor.from_checkpoints(coarse=ckpts["coarse"], models_dir=tiny_synth_root / "models")
    alone = plain.predict(ds.load_rgb(rec), rec.camera.K, detections=det)
    before = est.before_icp()
    assert before.icp is None and before.timings["icp"] == 0 and before.timings["total"] < est.timings["total"]
    np.testing.assert_allclose(before.TCO.numpy(), alone.TCO.numpy(), atol=1e-9)
    for k, r in enumerate(est.icp):
        np.testing.assert_allclose(est.TCO[k].numpy(), r.TCO, atol=1e-6)


class _NanNet(nn.Module):
    def forward(self, x):
        return torch.full((len(x), 9), float("nan"))


def test_nan_poses_are_flagged_and_never_written(tiny_synth_root, predictor, tmp_path):
    ds = BopDataset(tiny_synth_root)
    bad = Predictor(PoseModel(_NanNet(), "coarse", tuple(CROP), OBJ_IDS), predictor.refiner, predictor.objects,
                    predictor.renderer, config=InferenceConfig(n_refiner_iterations=1))
    with pytest.warns(RuntimeWarning, match="invalid poses"):
        summary = run_on_split(bad, ds, tmp_path, detections="oracle", progress=False)
    n_targets = sum(t.inst_count for t in ds.test_targets())
    assert summary.n_invalid == n_targets and summary.n_estimates == 0
    assert summary.csv_path.read_text() == HEADER


def test_clear_errors_for_bad_checkpoints(tiny_synth_root, ckpts, tmp_path, capsys):
    import infer

    def run(coarse, refiner):
        rc = infer.main(["--dataset", str(tiny_synth_root), "--coarse", str(coarse), "--refiner", str(refiner),
                         "--detections", "oracle", "--out", str(tmp_path), "--no-progress"])
        return rc, capsys.readouterr().err

    rc, err = run(tmp_path / "missing.pt", ckpts["refiner"])
    assert rc == 2 and "missing.pt" in err and "not found" in err
    rc, err = run(ckpts["refiner"], ckpts["refiner"])
    assert rc == 2 and str(ckpts["refiner"]) in err and "'refiner'" in err and "coarse" in err
    narrow = _save_pose_ckpt(tmp_path / "narrow.pt", "coarse", obj_ids=[1])
    rc, err = run(narrow, ckpts["refiner"])
    assert rc == 2 and "narrow.pt" in err and "covers obj_ids [1]" in err and "missing [" in err
    assert not list(tmp_path.glob("*.csv"))


def test_the_detector_feeds_predict_and_the_vivo_run(tiny_synth_root, ckpts, tmp_path):
    ds = BopDataset(tiny_synth_root)
    p = Predictor.from_checkpoints(detector=ckpts["detector"], coarse=ckpts["coarse"], dataset=tiny_synth_root)
    rec = next(ds.images("test"))
    est = p.predict(ds.load_rgb(rec), rec.camera.K)  # the untrained detector's detections, whatever they are
    assert est.timings["detection"] > 0 and len(est) <= 5 and bool(est.valid.all())
    summary = run_on_split(p, ds, tmp_path, progress=False)
    assert summary.ok and summary.timings["detection"] > 0
    targets = targets_by_image(ds.test_targets())
    for key, est in _rows_by_image(summary.csv_path).items():
        per_obj = defaultdict(int)
        for e in est:
            per_obj[e.obj_id] += 1
        assert all(n <= targets[key].get(o, 0) for o, n in per_obj.items())  # at most inst_count per target object
        assert len({e.time for e in est}) == 1


def _trained_statistics(net: nn.Module) -> None:
    """BatchNorm statistics of a trained network, not the identity of a fresh one."""
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)


def test_inference_net_folds_batchnorm_without_changing_outputs():
    from cosy_lite.inference.predictor import inference_net
    from cosy_lite.weights.pose_nets import PoseNetConfig, build_pose_net

    torch.manual_seed(0)
    net = build_pose_net(PoseNetConfig(backbone="resnet18", crop_resolution=CROP)).eval()
    nn.init.normal_(net.head.weight, std=0.01)
    _trained_statistics(net)
    fast = inference_net(net, torch.device("cpu"))
    assert not any(isinstance(m, nn.BatchNorm2d) for m in fast.modules())
    assert any(isinstance(m, nn.BatchNorm2d) for m in net.modules())  # the given network is untouched
    x = torch.rand(3, 6, *CROP)
    with torch.inference_mode():
        ref, out = net(x), fast(x.contiguous(memory_format=torch.channels_last))
    assert ref.abs().max() > 1e-3
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-5 * float(ref.abs().max()))


def test_inference_net_folds_the_flow_refiners_timm_batchnorm_act_layers():
    from timm.layers import BatchNormAct2d

    from cosy_lite.inference.torch_runtime import inference_net
    from cosy_lite.nets.flow_pose_net import FlowPoseNet

    torch.manual_seed(0)
    net = FlowPoseNet(pretrained=False, radius=2, descriptor=16).eval()
    _trained_statistics(net)
    n_act = sum(isinstance(m, BatchNormAct2d) for m in net.modules())
    assert n_act > 10  # the EfficientNet trunk's norms carry its activations
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # folded outputs equal: no fallback
        fast = inference_net(net, torch.device("cpu"), example_shape=(2, 6, 64, 96))
    assert not any(isinstance(m, nn.BatchNorm2d) for m in fast.modules())
    x = torch.rand(3, 6, 64, 96)
    with torch.inference_mode():
        ref, out = net(x), fast(x.contiguous(memory_format=torch.channels_last))
    assert ref.abs().max() > 1e-2
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-5 * float(ref.abs().max()))


class _NormBeforeConv(nn.Module):
    """A conv registered before its norm, but the norm runs first: folding by registration order is wrong."""

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(6, 6, 3, padding=1)
        self.norm = nn.BatchNorm2d(6)

    def forward(self, x):
        return self.conv(self.norm(x)).mean(dim=(2, 3))


def test_inference_net_keeps_a_network_whose_folded_copy_differs():
    from cosy_lite.inference.torch_runtime import inference_net
    from cosy_lite.nets.batchnorm_folding import fold_batchnorm

    torch.manual_seed(0)
    net = _NormBeforeConv().eval()
    _trained_statistics(net)
    assert fold_batchnorm(copy.deepcopy(net)) == 1  # registration order alone would fold it
    with pytest.warns(RuntimeWarning, match="BatchNorm folded gives other outputs"):
        kept = inference_net(net, torch.device("cpu"), example_shape=(2, 6, 8, 8))
    assert any(isinstance(m, nn.BatchNorm2d) for m in kept.modules())
    x = torch.rand(2, 6, 8, 8)
    with torch.inference_mode():
        torch.testing.assert_close(kept(x), net(x))


def test_valid_poses_and_orthonormalise():
    from cosy_lite.geometry.pose_checks import orthonormalise, valid_poses

    T = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    T[:, 2, 3] = 0.5
    T[1, 0, 0] = float("nan")
    T[2, 2, 3] = -0.5  # behind the camera
    T[3, :3, :3] *= 1.01  # not a rotation
    T[4, 0, 1] = 1e-4  # a rotation up to float32 noise
    assert valid_poses(T).tolist() == [True, False, False, False, True]
    fixed = orthonormalise(T)
    assert torch.isnan(fixed[1]).any() and valid_poses(fixed).tolist() == [True, False, False, True, True]
    R = fixed[4, :3, :3]
    assert float((R @ R.T - torch.eye(3, dtype=R.dtype)).abs().max()) < 1e-12


def test_the_refiner_depth_drift_divides_the_refined_depth_only(tiny_synth_root, ckpts, tmp_path):
    """InferenceConfig.refiner_depth_drift: the translation after N refiner iterations is divided by the N-th
    entry (the last one beyond); rotations unchanged; no refiner iteration, no correction."""
    ds = BopDataset(tiny_synth_root)
    kw = dict(coarse=ckpts["coarse"], refiner=ckpts["refiner"], dataset=ds)

    def run(name: str, **settings):
        s = run_on_split(Predictor.from_checkpoints(**kw, config=InferenceConfig(**settings)), ds, tmp_path / name,
                         method=name, detections="oracle", progress=False)
        return read_results_csv(s.csv_path)

    drift = [1.1, 1.25]
    plain, corrected = run("plain", n_refiner_iterations=2), run("drift", n_refiner_iterations=2, refiner_depth_drift=drift)
    beyond = run("beyond", n_refiner_iterations=3, refiner_depth_drift=drift)
    assert len(plain) == len(corrected) == len(beyond) > 0
    for a, b, c in zip(plain, corrected, beyond):
        assert (a.scene_id, a.im_id, a.obj_id) == (b.scene_id, b.im_id, b.obj_id)
        np.testing.assert_allclose(b.TCO[:3, :3], a.TCO[:3, :3], atol=1e-6)
        np.testing.assert_allclose(b.TCO[:3, 3], a.TCO[:3, 3] / 1.25, rtol=1e-5)  # 2 iterations: the 2nd entry
        np.testing.assert_allclose(c.TCO[:3, 3], a.TCO[:3, 3] / 1.25, rtol=1e-5)  # 3: the last entry
    no_refiner = run("none", n_refiner_iterations=0, refiner_depth_drift=drift)
    coarse_only = run("coarse", n_refiner_iterations=0)
    for a, b in zip(coarse_only, no_refiner):
        np.testing.assert_allclose(b.TCO, a.TCO, atol=1e-6)


def test_depth_from_mask_moves_the_depth_along_the_line_of_sight_towards_the_gt(tiny_synth_root, ckpts, tmp_path):
    """InferenceConfig.depth_from_mask with the GT masks (loaded for it): the same rotations and lines of
    sight as without, depths nearer the GT on average (the start's box depth errs and the untrained refiner
    keeps it; its rotations err too, so the gain is smaller than at a right rotation: test_mask_fit.py);
    boxes only: a warning, and the refiner's depth kept."""
    ds = BopDataset(tiny_synth_root)
    kw = dict(coarse=ckpts["coarse"], refiner=ckpts["refiner"], dataset=ds)

    def run(name: str, **settings):
        s = run_on_split(Predictor.from_checkpoints(**kw, config=InferenceConfig(n_refiner_iterations=1, **settings)),
                         ds, tmp_path / name, method=name, detections="oracle", progress=False)
        return read_results_csv(s.csv_path)

    plain, fitted = run("plain"), run("fitted", depth_from_mask=True)
    assert len(plain) == len(fitted) > 0
    errors = {"plain": [], "fitted": []}
    for a, b in zip(plain, fitted):
        assert (a.scene_id, a.im_id, a.obj_id) == (b.scene_id, b.im_id, b.obj_id)
        np.testing.assert_allclose(b.TCO[:3, :3], a.TCO[:3, :3], atol=1e-6)
        np.testing.assert_allclose(np.cross(a.TCO[:3, 3], b.TCO[:3, 3]) / np.linalg.norm(a.TCO[:3, 3]) ** 2, 0.0, atol=1e-6)
        gt = [g for g in ds.image("test", a.scene_id, a.im_id).gt if g.obj_id == a.obj_id]
        z_gt = min(g.TCO[2, 3] for g in gt) if len(gt) == 1 else None
        if z_gt is not None:
            errors["plain"].append(abs(a.TCO[2, 3] / z_gt - 1))
            errors["fitted"].append(abs(b.TCO[2, 3] / z_gt - 1))
    assert len(errors["plain"]) >= 5
    assert np.mean(errors["fitted"]) < 0.9 * np.mean(errors["plain"]), errors
    assert sum(abs(a.TCO[2, 3] - b.TCO[2, 3]) > 1e-6 for a, b in zip(plain, fitted)) >= len(plain) // 3
    rgb = np.asarray(ds.load_rgb(ds.image("test", plain[0].scene_id, plain[0].im_id)))
    boxes_only = Detections(torch.tensor([[100.0, 100.0, 180.0, 170.0]]), torch.tensor([OBJ_IDS[0]]), torch.tensor([0.9]))
    p = Predictor.from_checkpoints(**kw, config=InferenceConfig(n_refiner_iterations=1, depth_from_mask=True))
    with pytest.warns(RuntimeWarning, match="depth_from_mask .* boxes only"):
        est = p.predict(rgb, ds.image("test", plain[0].scene_id, plain[0].im_id).camera.K, detections=boxes_only)
    plain_est = Predictor.from_checkpoints(**kw, config=InferenceConfig(n_refiner_iterations=1)).predict(
        rgb, ds.image("test", plain[0].scene_id, plain[0].im_id).camera.K, detections=boxes_only)
    np.testing.assert_allclose(est.TCO.numpy(), plain_est.TCO.numpy(), atol=1e-9)


def test_the_silhouette_guard_keeps_an_iteration_with_its_own_depth_drift(tiny_synth_root, ckpts):
    """Predictor._refined_poses with silhouette_guard: given the refiner's iterations [GT, GT turned 40 deg]
    and the GT masks, the objects whose first iteration fits its mask clearly better keep it, divided by the
    drift after 1 iteration; the others keep the last, divided by the drift after 2; without the guard all keep
    the last."""
    from cosy_lite.inference.bop_run import detection_source

    ds = BopDataset(tiny_synth_root)
    key = ds.test_image_targets()[0]
    rec = ds.image("test", key.scene_id, key.im_id)
    det = detection_source("oracle", ds, with_masks=True)(rec)
    gt = {g.obj_id: g.TCO for g in rec.gt}
    ids = [int(i) for i in det.obj_ids if int(i) in gt]
    keep = [k for k, i in enumerate(det.obj_ids.tolist()) if i in ids]
    masks = det.masks[keep]
    first = torch.from_numpy(np.stack([gt[i] for i in ids]))
    turn = torch.from_numpy(np.array([[np.cos(0.7), 0, np.sin(0.7)], [0, 1, 0], [-np.sin(0.7), 0, np.cos(0.7)]]))
    last = first.clone()
    last[:, :3, :3] = turn @ first[:, :3, :3]
    drift = [1.1, 1.25]
    K = torch.from_numpy(rec.camera.K)
    for guard in (0.05, 0.0):
        p = Predictor.from_checkpoints(coarse=ckpts["coarse"], refiner=ckpts["refiner"], dataset=ds, config=InferenceConfig(
            n_refiner_iterations=2, refiner_depth_drift=drift, silhouette_guard=guard))
        assert p.reads_masks == (guard > 0)  # (a coarse start reads no masks of its own: the split run loads them for it)
        out = p._refined_poses(last, [first, last], K, masks, ids, p.renderer).numpy()
        went_back = [np.allclose(out[j, :3, :3], first[j, :3, :3].numpy()) for j in range(len(ids))]
        for j, back in enumerate(went_back):
            expected = first[j].numpy() if back else last[j].numpy()
            np.testing.assert_allclose(out[j, :3, :3], expected[:3, :3], atol=1e-9)
            np.testing.assert_allclose(out[j, :3, 3], expected[:3, 3] / (1.1 if back else 1.25), rtol=1e-9)
        assert sum(went_back) >= (len(ids) + 1) // 2 if guard else not any(went_back)

"""BOP 2024/2025 6D detection scores (eval_bop24_pose.py rules), every expectation computed by hand.

AP is COCO's: the mean over the 101 recall points 0, 0.01, .., 1 of the best precision at a recall
>= the point. With n GT and the first m of them found before any false positive (recall m/n,
precision 1), the points r <= m/n give 1: e.g. m/n = 1/2 -> 51 points, 1/3 -> 34, 2/3 -> 67.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bop_fixtures import GT, edit_json, scene_dir, write_tiny_bop

from cosy_lite.bop.results import PoseEstimate, write_results_csv
from cosy_lite.errors import BopFormatError
from cosy_lite.eval.pose_detection import (
    GroupErrors,
    average_precision,
    evaluate_6d_detection,
    object_average_precisions,
    score_groups,
    top_per_image,
)

INF = np.inf


def _group(scores, visib, mssd_norm, mspd_px=None, im_id=0, obj_id=1, width=640) -> GroupErrors:
    """A group with MSSD given as a fraction of a diameter of 1 m (so the error in m is the fraction)."""
    mssd = np.array(mssd_norm, dtype=np.float64).reshape(len(scores), len(visib))
    mspd = mssd * 100 if mspd_px is None else np.array(mspd_px, dtype=np.float64).reshape(mssd.shape)
    return GroupErrors(0, im_id, obj_id, np.array(scores, dtype=np.float64), np.array(visib, dtype=np.float64),
                       mssd, mspd, width)


# ----------------------------------------------------------------------------- AP and matching


def test_average_precision_by_hand():
    assert average_precision([1.0], [1.0]) == 1.0
    assert average_precision([], []) == 0.0
    assert average_precision([0.5, 0.5], [1.0, 0.5]) == pytest.approx(51 / 101)
    assert average_precision([0.0, 0.5], [0.0, 0.5]) == pytest.approx(0.5 * 51 / 101)
    # the toolkit's own example (score.py __main__): TP pattern F T T F T F over 6 GT
    tp = np.array([0, 1, 1, 0, 1, 0], dtype=bool)
    rec, pre = np.cumsum(tp) / 6, np.cumsum(tp) / np.arange(1, 7)
    # r <= 1/6: best precision 2/3 (17 points), r <= 2/6: 2/3 (17 more), r <= 3/6: 3/5 (17), above: 0
    assert average_precision(rec, pre) == pytest.approx((34 * 2 / 3 + 17 * 3 / 5) / 101)


def test_single_object_single_estimate():
    g = _group([0.9], [1.0], [0.22], mspd_px=[42.0])  # MSSD correct from the threshold 0.25 on: 6 of 10
    aps, n_gt = object_average_precisions([g], "mssd", 1.0)
    assert n_gt == 1 and aps.tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 1, 1]
    s = score_groups([g], {1: 1.0})
    assert s.map["mssd"] == pytest.approx(0.6) and s.bop25_map == pytest.approx(0.6)
    assert s.map["mspd"] == pytest.approx(0.2)  # 42 px: correct at 45 and 50 px
    assert s.bop24_map == pytest.approx(0.4)
    assert s.map["mssd_mm"] == 0.0  # 220 mm > 20 mm


def test_false_positives_before_and_after_the_true_one():
    fp_first = _group([0.9, 0.8], [1.0], [[INF], [0.01]])
    assert object_average_precisions([fp_first], "mssd", 1.0)[0] == pytest.approx(np.full(10, 0.5))
    fp_last = _group([0.9, 0.8], [1.0], [[0.01], [INF]])
    assert object_average_precisions([fp_last], "mssd", 1.0)[0] == pytest.approx(np.ones(10))


def test_a_duplicate_is_a_false_positive_and_matching_is_per_threshold():
    # A (0.9) is 0.12 off, B (0.8) 0.04: at 0.05 and 0.10 only B matches (A is a false positive before
    # it: AP 1/2); from 0.15 on A takes the GT and B is a duplicate after it (AP 1).
    g = _group([0.9, 0.8], [1.0], [[0.12], [0.04]])
    aps, _ = object_average_precisions([g], "mssd", 1.0)
    assert aps == pytest.approx([0.5, 0.5] + [1.0] * 8)
    assert score_groups([g], {1: 1.0}).map["mssd"] == pytest.approx(0.9)


def test_greedy_takes_the_lowest_error_free_gt():
    # two GT; the best estimate is closest to GT 1, the second only near GT 1 as well -> one match, one FP
    g = _group([0.9, 0.8], [1.0, 1.0], [[0.3, 0.02], [INF, 0.03]])
    aps, n_gt = object_average_precisions([g], "mssd", 1.0)
    # at every threshold est 1 takes GT 1 (its lowest error), est 2 finds no free GT: TP, FP, recall 1/2
    assert n_gt == 2
    assert aps == pytest.approx(np.full(10, 51 / 101))


def test_ignored_low_visibility_gt():
    # GT 0 is 5 % visible: not counted; the 0.9 estimate matched to it is dropped (not a FP).
    g = _group([0.9, 0.8], [0.05, 0.9], [[0.01, INF], [INF, 0.01]])
    aps, n_gt = object_average_precisions([g], "mssd", 1.0)
    assert n_gt == 1 and aps == pytest.approx(np.ones(10))
    # an object whose only GT is ignored is left out of the mean
    other = _group([0.7], [0.02], [[0.01]], obj_id=2)
    s = score_groups([g, other], {1: 1.0, 2: 1.0})
    assert s.n_gt == {1: 1, 2: 0} and s.map["mssd"] == pytest.approx(1.0)


def test_ties_follow_the_group_order():
    tp = _group([0.5], [1.0], [[0.01]], im_id=0)
    fp = _group([0.5], [1.0], [[INF]], im_id=1)
    assert object_average_precisions([tp, fp], "mssd", 1.0)[0] == pytest.approx(np.full(10, 51 / 101))
    assert object_average_precisions([fp, tp], "mssd", 1.0)[0] == pytest.approx(np.full(10, 0.5 * 51 / 101))


def test_mspd_thresholds_scale_with_the_image_width():
    g = _group([0.9], [1.0], [[INF]], mspd_px=[[12.0]], width=1280)  # 12 px at 1280 = 6 px at 640: 9 of 10
    assert object_average_precisions([g], "mspd", 1.0)[0].mean() == pytest.approx(0.9)


def test_top_100_per_image_is_stable():
    T = np.eye(4)
    T[2, 3] = 0.5
    ests = [PoseEstimate(0, 0, 1, 0.5, T) for _ in range(103)] + [PoseEstimate(0, 1, 1, 0.1, T)]
    ests[50].score = 0.9
    kept, dropped = top_per_image(ests)
    assert dropped == 3 and len(kept) == 101
    assert kept[0] is ests[50] and kept[1] is ests[0] and kept[50] is ests[49] and kept[99] is ests[99] and kept[100] is ests[103]


# ----------------------------------------------------------------------------- end to end on a BOP folder


def _gt_pose(im_id: int, gt_idx: int, shift_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    _, R, t_mm = GT[im_id][gt_idx]
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t_mm / 1000.0 + np.array(shift_m)
    return T


@pytest.fixture()
def root(tmp_path: Path) -> Path:
    root = write_tiny_bop(tmp_path)
    (root / "test_targets_bop24.json").write_text(json.dumps([{"im_id": 0, "scene_id": 0}, {"im_id": 1, "scene_id": 0}]))
    return root


def _evaluate(root: Path, ests: list[PoseEstimate]):
    csv = root.parent / "m_tiny-test.csv"
    write_results_csv(csv, ests)
    return evaluate_6d_detection(root, csv, progress=False)


def test_gt_poses_score_one(root: Path):
    ests = [PoseEstimate(0, im, GT[im][g][0], 1.0, _gt_pose(im, g), 0.2) for im in GT for g in range(len(GT[im]))]
    r = _evaluate(root, ests)
    assert r.scores.n_gt == {1: 3, 2: 2}
    assert r.scores.bop24_map == 1.0 and r.scores.bop25_map == 1.0 and r.scores.map["mssd_mm"] == 1.0
    assert r.average_time_per_image == pytest.approx(0.2)


def test_more_than_100_estimates_in_an_image(root: Path):
    far = (1.0, 0.0, 0.0)  # 1 m to the side: wrong for MSSD and MSPD
    ests = [PoseEstimate(0, 0, 2, 0.9, _gt_pose(0, 1, far), 0.1) for _ in range(100)]
    ests.append(PoseEstimate(0, 0, 1, 0.5, _gt_pose(0, 0), 0.1))  # correct, but the 101st of image 0
    ests += [PoseEstimate(0, 1, GT[1][g][0], 1.0, _gt_pose(1, g), 0.3) for g in range(3)]
    r = _evaluate(root, ests)
    assert r.n_estimates_dropped == 1 and r.n_estimates_evaluated == 103
    # obj 1: 3 GT, two found (recall 2/3 at precision 1): 67/101; obj 2: 2 GT, TP then 100 FP: 51/101
    for t in ("mssd", "mspd", "mssd_mm"):
        assert r.scores.ap[t][1] == pytest.approx(np.full(10, 67 / 101))
        assert r.scores.ap[t][2] == pytest.approx(np.full(10, 51 / 101))
    assert r.scores.bop24_map == pytest.approx(118 / 202)
    assert r.average_time_per_image == pytest.approx(0.2)


def test_ties_follow_the_targets_file_order(root: Path):
    ests = [PoseEstimate(0, 0, 1, 0.5, _gt_pose(0, 0), 0.1),  # TP in image 0
            PoseEstimate(0, 1, 1, 0.5, _gt_pose(1, 0, (0.5, 0.0, 0.0)), 0.1)]  # FP in image 1, same score
    r = _evaluate(root, ests)
    assert r.scores.ap["mssd"][1] == pytest.approx(np.full(10, 34 / 101))  # TP first: recall 1/3 at 1
    assert r.scores.bop25_map == pytest.approx(17 / 101)  # obj 2 (2 GT, nothing found) scores 0
    (root / "test_targets_bop24.json").write_text(json.dumps([{"im_id": 1, "scene_id": 0}, {"im_id": 0, "scene_id": 0}]))
    r = _evaluate(root, ests)
    assert r.scores.ap["mssd"][1] == pytest.approx(np.full(10, 17 / 101))  # FP first: precision 1/2


def test_low_visibility_gt_is_ignored_end_to_end(root: Path):
    edit_json(scene_dir(root) / "scene_gt_info.json", lambda d: d["1"][0].update(visib_fract=0.05))
    ests = [PoseEstimate(0, 1, 1, 0.9, _gt_pose(1, 0), 0.1),  # matches the ignored GT: dropped
            PoseEstimate(0, 0, 1, 0.8, _gt_pose(0, 0), 0.1),  # TP
            PoseEstimate(0, 0, 5, 0.95, _gt_pose(0, 0), 0.1)]  # an object absent from the image: not evaluated
    r = _evaluate(root, ests)
    assert r.scores.n_gt[1] == 2 and r.n_estimates_evaluated == 2
    assert r.scores.ap["mssd"][1] == pytest.approx(np.full(10, 51 / 101))


def test_eval_command_6d_detection(root: Path, capsys, monkeypatch):
    from cosy_lite.cli import main

    ests = [PoseEstimate(0, im, GT[im][g][0], 1.0, _gt_pose(im, g), 0.2) for im in GT for g in range(len(GT[im]))]
    csv = root.parent / "m_tiny-test.csv"
    write_results_csv(csv, ests)
    monkeypatch.chdir(root.parent)
    assert main(["eval", "--dataset", str(root), "--results", str(csv), "--task", "6d-detection", "--no-progress"]) == 0
    scores = json.loads((root.parent / "outputs" / "eval" / "m_tiny-test" / "scores_bop24.json").read_text())
    assert scores["bop24_mAP"] == 1.0 and scores["bop25_mAP"] == 1.0 and scores["bop24_mAP_mspd"] == 1.0
    assert "bop24_mAP 1.0000" in capsys.readouterr().out
    (root / "test_targets_bop24.json").unlink()
    assert main(["eval", "--dataset", str(root), "--results", str(csv), "--task", "6d-detection"]) != 0
    assert "test_targets_bop24.json" in capsys.readouterr().out


# ----------------------------------------------------------------------------- the targets file


def test_bop24_targets_are_read_and_checked(root: Path):
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.validate import check_dataset

    assert [(t.scene_id, t.im_id) for t in BopDataset(root).test_image_targets()] == [(0, 0), (0, 1)]
    assert [p for p in check_dataset(root) if "bop24" in p.path] == []
    path = root / "test_targets_bop24.json"
    path.write_text(json.dumps([{"im_id": 0, "scene_id": 0}, {"im_id": 7, "scene_id": 0}, {"im_id": 0, "scene_id": 3},
                                {"im_id": 0, "scene_id": 0}]))
    found = {(p.field, p.severity) for p in check_dataset(root) if p.path == str(path)}
    assert found == {("[1].im_id", "error"), ("[2].scene_id", "error"), ("[3]", "warning")}
    path.write_text(json.dumps([{"im_id": -1, "scene_id": 0}]))
    with pytest.raises(BopFormatError, match=r"test_targets_bop24.json \[\[0\].im_id\]: expected a non-negative integer"):
        BopDataset(root).test_image_targets()


def test_eval_command_6d_detection_scores_unknown_object_ids_as_the_toolkit(root: Path, capsys):
    """The toolkit's checker accepts estimates of objects the dataset lacks and eval_bop24_pose.py
    scores the file: they take places among an image's 100 best estimates and match no GT."""
    from cosy_lite.cli import main

    gt_ests = [PoseEstimate(0, im, GT[im][g][0], 1.0, _gt_pose(im, g), 0.2) for im in GT for g in range(len(GT[im]))]
    csv = root.parent / "m_tiny-test.csv"

    def bop24_map(unknown: list[PoseEstimate]) -> float:
        write_results_csv(csv, gt_ests + unknown)
        assert main(["eval", "--dataset", str(root), "--results", str(csv), "--task", "6d-detection",
                     "--no-progress", "--out", str(root.parent / "ev")]) == 0
        return json.loads((root.parent / "ev" / "scores_bop24.json").read_text())["bop24_mAP"]

    # 5 estimates of obj 7 scored below the GT estimates: nothing changes
    assert bop24_map([PoseEstimate(0, 0, 7, 0.5, _gt_pose(0, 0), 0.2)] * 5) == 1.0
    out = capsys.readouterr().out
    assert out.count("obj_ids 7 are not in") == 1 and "(5 estimates)" in out
    # 100 of them above: image 0 keeps only those, so obj 1 is found 2 of 3 times (67 of the 101
    # recall points) and obj 2 once of 2 (51 points), at every threshold of both errors
    assert bop24_map([PoseEstimate(0, 0, 7, 2.0, _gt_pose(0, 0), 0.2)] * 100) == pytest.approx((67 + 51) / 2 / 101)
    # the BOP19 task keeps refusing them (its targets name every scored object)
    assert main(["eval", "--dataset", str(root), "--results", str(csv), "--no-progress"]) == 1
    assert "obj_id 7 is not in" in capsys.readouterr().out


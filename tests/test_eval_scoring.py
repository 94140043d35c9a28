"""BOP19 scoring: greedy matching, recalls and AR with hand-computed values; the evaluator and the
``eval`` command end to end on the tiny BOP fixture (GT poses written as estimates)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bop_fixtures import GT, edit_json, scene_dir, write_tiny_bop

from cosy_lite.bop.results import PoseEstimate, write_results_csv
from cosy_lite.eval.scoring import (
    VSD_TAUS,
    TargetErrors,
    auc_threshold_curve,
    match_greedy,
    score_targets,
    valid_gt,
)

# ----------------------------------------------------------------------------- matching


def test_match_greedy_takes_best_unmatched_gt_in_score_order():
    errors = np.array([[1.0, 2.0], [0.5, 3.0]])  # est 0 (higher score) x GT 0, 1
    valid = np.array([True, True])
    # est 0 takes GT 0 (its best); est 1's best remaining is GT 1 at 3.0.
    np.testing.assert_array_equal(match_greedy(errors, valid, [2.5, 5.0]), [[0, -1], [0, 1]])
    # Strict "<": est 0 (error 1.0 = threshold) does not match; GT 0 stays free for est 1.
    np.testing.assert_array_equal(match_greedy(errors, valid, [1.0]), [[1, -1]])


def test_match_greedy_ignores_invalid_gt_and_nan():
    errors = np.array([[1.0, 0.5]])
    np.testing.assert_array_equal(match_greedy(errors, np.array([True, False]), [2.0]), [[0, -1]])
    np.testing.assert_array_equal(match_greedy(np.array([[np.nan]]), np.array([True]), [np.inf]), [[-1]])
    assert match_greedy(np.zeros((2, 0)), np.zeros(0, bool), [1.0]).shape == (1, 0)


def _target(obj_id: int, errs: list[list[float]], valid: list[bool], mspd=None, im_id: int = 0) -> TargetErrors:
    """All metrics share ``errs`` [E,G] (MSSD in m, MSPD in px unless given, VSD the same for every tau)."""
    e = np.array(errs, dtype=np.float64).reshape(len(errs), len(valid))
    return TargetErrors(
        0, im_id, obj_id, max(len(errs), 1), np.linspace(1, 0.5, len(errs)), np.array(valid),
        np.repeat(e[:, :, None], len(VSD_TAUS), axis=2), e, e if mspd is None else np.array(mspd, dtype=np.float64),
        e, e,
    )


DIAM = {1: 0.1, 2: 0.2}


def test_perfect_and_missing_estimates():
    perfect = [_target(1, [[0.0]], [True], im_id=i) for i in range(3)]
    s = score_targets(perfect, DIAM, 640)
    assert (s.ar, s.ar_vsd, s.ar_mssd, s.ar_mspd) == (1.0, 1.0, 1.0, 1.0)
    assert s.auc_add_s == pytest.approx(1.0) and s.n_targets == 3
    missing = TargetErrors.empty(0, 3, 1, 1, np.array([True]))
    s = score_targets(perfect + [missing], DIAM, 640)
    assert s.ar == pytest.approx(0.75) and s.recall_mssd.tolist() == [0.75] * 10
    assert s.n_targets == 4 and s.n_estimates == 3


def test_mssd_thresholds_scale_with_diameter_and_per_object_recall():
    # MSSD 0.012 m: for diameter 0.1 it is < 0.15 d (8 of 10 thresholds); for 0.2: < 0.1 d (9 of 10).
    s = score_targets([_target(1, [[0.012]], [True]), _target(2, [[0.012]], [True])], DIAM, 640)
    assert s.per_object[1].recall_mssd.sum() == pytest.approx(8)
    assert s.per_object[2].recall_mssd.sum() == pytest.approx(9)
    assert s.ar_mssd == pytest.approx(0.85)


@pytest.mark.parametrize("width, n_correct", [(640, 9), (1280, 10), (320, 8)])
def test_mspd_threshold_scaling_with_image_width(width: int, n_correct: int):
    # 7 px: at 640 px thresholds 5..50 -> 9 correct; 1280 -> 10..100: 10; 320 -> 2.5..25: 8.
    s = score_targets([_target(1, [[0.0]], [True], mspd=[[7.0]])], DIAM, width)
    assert s.recall_mspd.sum() == pytest.approx(n_correct)
    np.testing.assert_allclose(s.mspd_thresholds_px, np.arange(5, 51, 5) * width / 640)


def test_vsd_recall_per_tau_and_theta():
    t = _target(1, [[0.0]], [True])
    t.vsd[0, 0] = np.where(VSD_TAUS < 0.25, 0.6, 0.12)  # bad for small tau, < theta >= 0.15 for large tau
    s = score_targets([t], DIAM, 640)
    big = VSD_TAUS >= 0.25
    assert s.recall_vsd[~big].sum() == 0
    np.testing.assert_array_equal(s.recall_vsd[big], np.tile((np.arange(0.05, 0.51, 0.05) > 0.12), (big.sum(), 1)))
    assert s.ar_vsd == pytest.approx(big.sum() * 8 / 100)


def test_gt_below_visibility_is_not_a_target():
    # Estimate exactly on the invalid GT (visib_fract < 0.1): no match there, not in the denominator.
    s = score_targets([_target(1, [[1.0, 0.0]], [True, False], mspd=[[100.0, 0.0]])], DIAM, 640)
    assert s.n_targets == 1 and s.ar == 0.0
    s = score_targets([_target(1, [[0.0, 0.0]], [True, False])], DIAM, 640)
    assert s.n_targets == 1 and s.ar == 1.0


def test_valid_gt_rules():
    v = np.array([0.05, 1.0, 0.5, 0.5])
    np.testing.assert_array_equal(valid_gt(v, 2), [False, True, True, False])  # 2 most visible, GT order on ties
    np.testing.assert_array_equal(valid_gt(v, 0), [False] * 4)
    np.testing.assert_array_equal(valid_gt(v, 2, visib_gt_min=0.1), [False, True, True, True])


def test_no_target_gives_zero_recall():
    s = score_targets([TargetErrors.empty(0, 0, 1, 1, np.array([False]))], DIAM, 640)
    assert s.n_targets == 0 and s.ar == 0.0


def test_auc_threshold_curve():
    assert auc_threshold_curve(np.array([0.0, np.inf])) == pytest.approx(0.5)
    assert auc_threshold_curve(np.array([0.05])) == pytest.approx(0.5)
    assert auc_threshold_curve(np.array([0.02, 0.12])) == pytest.approx(0.4)
    assert auc_threshold_curve(np.array([])) == 0.0


# ----------------------------------------------------------------------------- evaluator on the fixture


def _gt_estimates() -> list[PoseEstimate]:
    out = []
    for im_id, insts in GT.items():
        for obj_id, R, t in insts:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t / 1000.0
            out.append(PoseEstimate(0, im_id, obj_id, 0.9, T, 0.1))
    return out


@pytest.fixture
def root(tmp_path: Path) -> Path:
    pytest.importorskip("pyrender")
    return write_tiny_bop(tmp_path)


def _evaluate(root: Path, ests: list[PoseEstimate], **kwargs):
    from cosy_lite.eval.evaluator import evaluate

    csv = root.parent / "gt_tiny-test.csv"
    write_results_csv(csv, ests)
    return evaluate(root, csv, progress=False, **kwargs)


def test_gt_as_estimate_scores_one(root: Path):
    r = _evaluate(root, _gt_estimates(), auc=True)
    s = r.scores
    assert (s.ar, s.ar_vsd, s.ar_mssd, s.ar_mspd) == (1.0, 1.0, 1.0, 1.0)
    assert s.n_targets == 5 and r.n_estimates_evaluated == 5 and r.im_width == 640
    assert s.auc_add_s == pytest.approx(1.0) and s.auc_adi == pytest.approx(1.0)
    assert sorted(s.per_object) == [1, 2] and s.per_object[1].n_targets == 3


def test_the_auc_is_computed_only_when_asked_and_changes_no_bop19_score(root: Path):
    # BOP19 (the default, as the toolkit) has no ADD/ADI: the AUC is None, in the JSON null and "-" in
    # the table; every AR equals the run with the AUC, on estimates off by 1-3 cm and 5-20 deg.
    from cosy_lite.eval.command import format_table
    from cosy_lite.geometry.transforms import rotation_about_axis

    ests = _gt_estimates()
    for k, e in enumerate(ests):
        e.TCO[:3, :3] = e.TCO[:3, :3] @ rotation_about_axis(np.array([1.0, 1.0, 0.0]) / np.sqrt(2), np.deg2rad(5 + 4 * k))
        e.TCO[:3, 3] += [0.01 * (k % 3), 0.0, 0.01]
    plain, full = _evaluate(root, ests), _evaluate(root, ests, auc=True)
    assert plain.scores.auc_add_s is None and plain.scores.auc_adi is None
    assert all(x.auc_add_s is None for x in plain.scores.per_object.values())
    assert 0.0 < full.scores.auc_add_s < 1.0 and 0.0 < plain.scores.ar < 1.0
    for k in ("ar", "ar_vsd", "ar_mssd", "ar_mspd"):
        assert getattr(plain.scores, k) == getattr(full.scores, k), k
    d = plain.to_dict()
    assert d["auc_add_s"] is None and d["per_object"]["1"]["auc_adi"] is None
    row = [line for line in format_table(plain).splitlines() if line.split()[:1] == ["all"]][0]
    assert row.split()[-2:] == ["-", "-"]


@pytest.mark.parametrize("start", ["spawn", "fork"])
def test_worker_processes_give_the_same_errors_and_scores(root: Path, monkeypatch, start: str):
    """evaluate(workers=2): the images split between two processes, spawned or forked (what
    ``cosy-lite eval`` does, free of torch); every error array and score equals the one-process run
    (estimates off by 1-3 cm and 5-20 deg, with the AUC)."""
    from cosy_lite.eval import evaluator
    from cosy_lite.geometry.transforms import rotation_about_axis

    monkeypatch.setattr(evaluator, "fork_is_safe", lambda: start == "fork")

    ests = _gt_estimates()
    for k, e in enumerate(ests):
        e.TCO[:3, :3] = e.TCO[:3, :3] @ rotation_about_axis(np.array([0.0, 1.0, 1.0]) / np.sqrt(2), np.deg2rad(5 + 4 * k))
        e.TCO[:3, 3] += [0.0, 0.01 * (k % 3), 0.01]
    import multiprocessing

    calls: list[int] = []  # before_errors: once, before any worker is forked
    one = _evaluate(root, ests, auc=True, before_errors=lambda: calls.append(len(multiprocessing.active_children())))
    two = _evaluate(root, ests, auc=True, workers=2,
                    before_errors=lambda: calls.append(len(multiprocessing.active_children())))
    assert calls == [0, 0]
    assert len(one.targets) == len(two.targets) > 1 and 0.0 < one.scores.ar < 1.0
    for a, b in zip(one.targets, two.targets):
        assert (a.scene_id, a.im_id, a.obj_id) == (b.scene_id, b.im_id, b.obj_id)
        for f in ("scores", "gt_valid", "vsd", "mssd", "mspd", "add", "adi"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f
    d1, d2 = one.to_dict(), two.to_dict()
    d1.pop("seconds"), d2.pop("seconds")
    assert d1 == d2
    with pytest.raises(ValueError, match="workers"):
        _evaluate(root, ests, workers=0)


def test_missing_estimate_lowers_recall_by_its_share(root: Path):
    ests = [e for e in _gt_estimates() if not (e.im_id == 0 and e.obj_id == 2)]
    s = _evaluate(root, ests).scores
    assert (s.ar_vsd, s.ar_mssd, s.ar_mspd) == (pytest.approx(0.8),) * 3
    assert s.per_object[2].ar == pytest.approx(0.5) and s.per_object[1].ar == pytest.approx(1.0)


def test_higher_scored_wrong_estimate_is_the_one_evaluated(root: Path):
    ests = _gt_estimates()
    wrong = PoseEstimate(0, 0, 1, 0.95, ests[0].TCO.copy(), 0.1)  # im 0, obj 1: inst_count 1
    wrong.TCO[:3, 3] += [0.2, 0.0, 0.0]
    r = _evaluate(root, ests + [wrong])
    assert r.n_estimates_in_file == 6 and r.n_estimates_evaluated == 5
    assert r.scores.ar == pytest.approx(0.8)
    # With a lower score the wrong one is cut by inst_count = 1.
    wrong.score = 0.5
    assert _evaluate(root, ests + [wrong]).scores.ar == pytest.approx(1.0)


def test_equal_scores_keep_file_order(root: Path):
    # The toolkit sorts with Python's stable sorted(..., reverse=True): on equal scores the
    # estimate written first is the one kept by inst_count = 1.
    ests = _gt_estimates()
    wrong = PoseEstimate(0, 0, 1, ests[0].score, ests[0].TCO.copy(), 0.1)
    wrong.TCO[:3, 3] += [0.2, 0.0, 0.0]
    assert _evaluate(root, [wrong] + ests).scores.ar == pytest.approx(0.8)
    assert _evaluate(root, ests + [wrong]).scores.ar == pytest.approx(1.0)


def test_repeated_target_entry_counts_once(root: Path):
    # The toolkit keys targets by (scene, image, object): a repeated entry replaces the first.
    def repeat(targets):
        targets.append(dict(targets[2], inst_count=1))  # (0, 1, 1) again, now with inst_count 1

    edit_json(root / "test_targets_bop19.json", repeat)
    r = _evaluate(root, _gt_estimates())
    assert r.scores.n_targets == 4 and r.n_estimates_evaluated == 4 and r.scores.ar == pytest.approx(1.0)


def test_gt_with_low_visibility_is_not_a_target(root: Path):
    def low(d):
        d["1"][0]["visib_fract"] = 0.05  # im 1, first obj-1 instance

    def one(targets):
        targets[2]["inst_count"] = 1  # (0, 1, 1): one instance visible enough, as BOP makes targets

    edit_json(scene_dir(root) / "scene_gt_info.json", low)
    ests = [e for e in _gt_estimates() if not (e.im_id == 0 and e.obj_id == 1)]
    ests[1].score = 0.5  # im 1: the estimate of the hidden instance ranks below the visible one's
    s = _evaluate(root, ests).scores
    assert s.n_targets == 5 and s.ar == pytest.approx(0.8)  # inst_count 2: both instances are targets
    edit_json(root / "test_targets_bop19.json", one)
    s = _evaluate(root, ests).scores
    assert s.n_targets == 4 and s.ar == pytest.approx(0.75)
    # The threshold rule (visib_fract >= 0.1) gives the same with consistent targets.
    s = _evaluate(root, ests, visib_gt_min=0.1).scores
    assert s.n_targets == 4 and s.ar == pytest.approx(0.75)


def test_eval_command_writes_json_and_png(root: Path, capsys):
    from cosy_lite.cli import main

    csv = root.parent / "gt_tiny-test.csv"
    write_results_csv(csv, _gt_estimates())
    out = root.parent / "out"
    assert main(["eval", "--dataset", str(root), "--results", str(csv), "--out", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "AR_MSSD" in text and "1.0000" in text
    data = json.loads((out / "scores.json").read_text())
    assert data["ar"] == 1.0 and data["per_object"]["2"]["ar_vsd"] == 1.0 and len(data["recall_vsd"]) == 10
    assert (out / "recall_curves.png").stat().st_size > 1000


def test_eval_program_ends_at_once_with_its_outputs_complete(root: Path):
    # ``python -m cosy_lite.cli eval`` (what the console script runs): two forked workers, the depth
    # decoded ahead, the process ended without the interpreter's teardown; the table, the JSON and
    # the PNG are complete, and a bad file still exits 1 with its report.
    csv = root.parent / "gt_tiny-test.csv"
    write_results_csv(csv, _gt_estimates())
    out = root.parent / "out"
    cmd = [sys.executable, "-m", "cosy_lite.cli", "eval", "--dataset", str(root), "--results", str(csv), "--out",
           str(out), "--no-progress", "--workers", "2"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "AR_MSSD" in r.stdout and r.stdout.rstrip().endswith("recall_curves.png")
    assert json.loads((out / "scores.json").read_text())["ar"] == 1.0
    assert (out / "recall_curves.png").stat().st_size > 1000
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n0,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 x,0.1\n")
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "FAILED" in r.stdout


def test_a_depth_that_fails_to_decode_ahead_is_reported_by_its_worker(root: Path, monkeypatch):
    # The prefetch thread decodes in image order and stops at the first image it cannot load; the
    # worker that evaluates that image raises the error naming the file, as without the prefetch.
    from cosy_lite.errors import BopFormatError
    from cosy_lite.eval import evaluator

    depth = sorted((scene_dir(root) / "depth").glob("*.png"))[1]
    depth.write_bytes(b"not a png")
    csv = root.parent / "gt_tiny-test.csv"
    write_results_csv(csv, _gt_estimates())
    ev = evaluator._ImageEvaluation(root, csv, None, None, 0.01, True, -1.0, False)
    keys = sorted(ev.by_image)
    prefetch = evaluator._DepthPrefetch(ev, keys)
    prefetch.start()
    prefetch.join()  # (run to its end: no stop)
    assert list(ev.depths) == keys[:1] and ev.depths[keys[0]].dtype == np.float32
    monkeypatch.setattr(evaluator, "fork_is_safe", lambda: True)
    with pytest.raises(BopFormatError, match=depth.name):
        _evaluate(root, _gt_estimates(), workers=2)


def test_eval_command_reports_images_without_estimates(root: Path, capsys):
    """Images whose targets got no estimate count as missed, and the report says which (it said nothing)."""
    from cosy_lite.cli import main

    ests = _gt_estimates()
    first = min(e.im_id for e in ests)
    csv = root.parent / "gt_tiny-test.csv"
    write_results_csv(csv, [e for e in ests if e.im_id != first])
    out = root.parent / "out"
    assert main(["eval", "--dataset", str(root), "--results", str(csv), "--out", str(out), "--no-progress"]) == 0
    n_images = len(GT)
    assert f"1 of {n_images} target images have no estimate (their targets count as missed): scene 0 image {first}" \
        in capsys.readouterr().out
    data = json.loads((out / "scores.json").read_text())
    assert data["images_without_estimates"] == [[0, first]] and data["n_images"] == n_images


def test_eval_command_stops_on_invalid_csv(root: Path, capsys):
    from cosy_lite.eval import command

    csv = root.parent / "gt_tiny-test.csv"
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n0,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 x,0.1")
    args = argparse.Namespace(dataset=str(root), results=csv, split=None, name=None, out=None,
                              max_sym_disc_step=0.01, sym_zero_angle=True, visib_gt_min=-1.0, no_progress=True)
    assert command.run(args) == 1
    assert "FAILED" in capsys.readouterr().out
    assert not (root.parent / "gt_tiny-test_eval").exists()




def _match_loop(errors: np.ndarray, valid: np.ndarray, th: float) -> list[int]:
    """The toolkit's match_poses, written as its loops (estimates already in score order)."""
    matched: list[int] = []
    out = [-1] * errors.shape[1]
    for e, row in enumerate(errors):
        best_gt, best_err = -1, th
        for g, err in enumerate(row):
            if valid[g] and g not in matched and err < best_err:
                best_gt, best_err = g, err
        if best_gt >= 0:
            matched.append(best_gt)
            out[best_gt] = e
    return out


def test_match_greedy_equals_the_toolkit_loop_on_random_cases():
    rng = np.random.default_rng(0)
    for _ in range(200):
        E, G = rng.integers(0, 5), rng.integers(0, 5)
        errors = np.round(rng.random((E, G)), 1)  # rounding makes ties
        valid = rng.random(G) < 0.8
        th = np.array([0.05, 0.3, 0.5, 0.9])
        got = match_greedy(errors, valid, th)
        for k, t in enumerate(th):
            assert got[k].tolist() == _match_loop(errors, valid, t)


def test_ar_core_is_the_mean_over_core_datasets():
    from cosy_lite.eval.scoring import ar_core

    ars = {"lmo": 0.6, "tless": 0.5, "tudl": 0.7, "icbin": 0.4, "itodd": 0.3, "hb": 0.8, "ycbv": 0.9, "tiny": 0.0}
    assert ar_core(ars) == pytest.approx(4.2 / 7)
    assert ar_core({"a": 0.2, "b": 0.4}, core=("a", "b")) == pytest.approx(0.3)
    with pytest.raises(KeyError, match="ycbv"):
        ar_core({k: v for k, v in ars.items() if k != "ycbv"})


def test_auc_of_add_s_uses_adi_for_objects_with_symmetries(root: Path):
    # "tiny" declares no ADD-S objects in the table, so those with symmetries in models_info (obj 2)
    # are scored with ADI. Obj 2 is a 50 x 50 x 80 mm box (8 vertices): turned 90 deg about z, its
    # vertex set maps onto itself (ADI 0) while every corner moves 50 mm (ADD 0.05 m, AUC 0.5).
    ests = _gt_estimates()
    for e in ests:
        if e.obj_id == 2:
            e.TCO[:3, :3] = e.TCO[:3, :3] @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    s = _evaluate(root, ests, auc=True).scores
    assert s.per_object[2].auc_add_s == pytest.approx(1.0) and s.per_object[2].auc_adi == pytest.approx(1.0)
    assert s.per_object[1].auc_add_s == pytest.approx(1.0)


def test_auc_matching_ignores_errors_of_10_cm_and_more():
    # Two GT instances; the higher-scored estimate is >= 10 cm from both (it adds nothing and takes
    # nothing), the second is 1 cm from GT 0: AUC = mean(0.9, 0) = 0.45. (Taking GT 0 with 15 cm
    # would push the second estimate onto GT 1 at 50 cm: AUC 0.)
    s = score_targets([_target(1, [[0.15, 0.2], [0.01, 0.5]], [True, True])], DIAM, 640)
    assert s.auc_add_s == pytest.approx(0.45) and s.auc_adi == pytest.approx(0.45)


def test_dataset_missing_from_the_table(tmp_path: Path):
    # No parameter-table entry: split "test", image width from the depth image, delta 15 mm.
    pytest.importorskip("pyrender")
    root = write_tiny_bop(tmp_path, name="mytiny")
    r = _evaluate(root, _gt_estimates())
    assert (r.dataset, r.split, r.im_width, r.vsd_delta) == ("mytiny", "test", 640, 0.015)
    assert r.scores.ar == 1.0


def test_estimates_outside_the_targets_are_ignored(root: Path):
    # The toolkit only visits targets: an estimate of an image (or object) without a target is not evaluated.
    ests = _gt_estimates()
    stray = PoseEstimate(0, 7, 1, 1.0, ests[0].TCO.copy(), 0.1)
    r = _evaluate(root, ests + [stray])
    assert r.n_estimates_in_file == 6 and r.n_estimates_evaluated == 5 and r.scores.ar == 1.0


class _InlineExecutor:
    """The evaluator's pool replaced by one that runs each job at once: every target's model errors
    are complete before the next target renders (the order of the implementation before the jobs were
    deferred to the end of the run)."""

    def __init__(self, *_):
        pass

    def submit(self, fn, *args):
        from concurrent.futures import Future

        f = Future()
        f.set_result(fn(*args))
        return f

    def shutdown(self, cancel_futures: bool = False) -> None:
        pass


def _noisy_estimates(seed: int = 0) -> list[PoseEstimate]:
    """2-3 estimates per target: GT + noise (up to 20 deg, 15 mm), a far-off one and a tie in score."""
    from cosy_lite.geometry.transforms import rotation_about_axis

    rng = np.random.default_rng(seed)
    out = []
    for e in _gt_estimates():
        for k in range(2 + int(rng.integers(0, 2))):
            T = e.TCO.copy()
            T[:3, :3] = rotation_about_axis(rng.normal(size=3), np.deg2rad(rng.uniform(0, 20))) @ T[:3, :3]
            T[:3, 3] += rng.normal(scale=0.015 if k < 2 else 0.08, size=3)
            out.append(PoseEstimate(0, e.im_id, e.obj_id, float(rng.choice([0.3, 0.5, 0.5, 0.9])), T, 0.1))
    return out


def test_deferred_model_errors_give_identical_errors_and_scores(root: Path, monkeypatch):
    # The pool's MSSD/MSPD/ADD/ADI jobs are awaited once all images are rendered; every error and
    # score must equal, bit for bit, those of the serial order (each target's errors before the next).
    from cosy_lite.eval import evaluator

    ests = _noisy_estimates()
    deferred = _evaluate(root, ests)
    monkeypatch.setattr(evaluator, "ThreadPoolExecutor", _InlineExecutor)
    serial = _evaluate(root, ests)
    assert deferred.n_estimates_evaluated == serial.n_estimates_evaluated == 5  # top inst_count per target
    for a, b in zip(deferred.targets, serial.targets, strict=True):
        for name in ("scores", "vsd", "mssd", "mspd", "add", "adi"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert 0.0 < deferred.scores.ar < 1.0
    assert deferred.to_dict() | {"seconds": 0} == serial.to_dict() | {"seconds": 0}


def test_error_in_a_deferred_job_is_raised(root: Path, monkeypatch):
    from cosy_lite.eval.object_errors import ObjectErrors

    def broken(*_, **__):
        raise FloatingPointError("model errors failed")

    for method, auc in (("mssd_mspd", False), ("adi", True)):
        with monkeypatch.context() as m:
            m.setattr(ObjectErrors, method, broken)
            with pytest.raises(FloatingPointError, match="model errors failed"):
                _evaluate(root, _gt_estimates(), auc=auc)


def test_auto_workers_follow_cores_and_split_size(monkeypatch):
    """cosy-lite eval's default (workers=None): one process per core, at most 4, one per 10 images."""
    import os

    from cosy_lite.eval import evaluator

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert [evaluator.auto_workers(n) for n in (1, 19, 20, 100, 10_000)] == [1, 1, 2, 2, 2]
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)
    assert [evaluator.auto_workers(n) for n in (9, 35, 100)] == [1, 3, 4]
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert evaluator.auto_workers(1000) == 1


def test_workers_are_forked_only_from_a_process_without_torch():
    code = ("import cosy_lite.eval.evaluator as e; a = e.fork_is_safe(); import torch; "
            "print(a, e.fork_is_safe())")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0 and r.stdout.split() == ["True", "False"], r.stdout + r.stderr


def test_an_exception_before_the_errors_stops_the_evaluation_before_any_worker(root: Path, monkeypatch):
    # (cosy-lite eval's rejection of bad input found by checks running beside the preparation)
    from cosy_lite.eval import evaluator

    def no_workers(*args, **kwargs):
        raise AssertionError("workers started")

    def rejected():
        raise LookupError("rejected by the checks")

    monkeypatch.setattr(evaluator, "fork_is_safe", lambda: True)
    monkeypatch.setattr(evaluator, "_parallel_errors", no_workers)
    with pytest.raises(LookupError, match="rejected"):
        _evaluate(root, _gt_estimates(), workers=2, before_errors=rejected)


def test_numba_starts_without_scipy_linalg_which_stays_importable():
    code = ("import sys\nfrom cosy_lite.eval.evaluator import import_numba_without_blas\n"
            "import_numba_without_blas()\nassert 'numba.np.arraymath' in sys.modules\n"
            "assert 'scipy.linalg' not in sys.modules\n"
            "from cosy_lite.render.depth_raster import warm_up\nwarm_up()\n"
            "assert 'scipy.linalg' not in sys.modules\n"
            "import scipy.linalg\nprint(scipy.linalg.det([[2.0, 0.0], [0.0, 3.0]]))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "6.0"


def test_guided_chunks_cover_the_keys_in_order_and_shrink():
    from cosy_lite.eval.evaluator import guided_chunks

    chunks = guided_chunks(list(range(100)), 2)
    assert [k for c in chunks for k in c] == list(range(100))
    sizes = [len(c) for c in chunks]
    assert sizes[0] == 25 and sizes[-1] == 1 and sizes == sorted(sizes, reverse=True)
    assert guided_chunks([], 2) == [] and guided_chunks(["a"], 4) == [["a"]]


def test_recall_figure_draws_the_curves_over_axes_drawn_ahead(root: Path, tmp_path: Path):
    # cosy-lite eval draws the axes while the errors are computed, then only the curves and titles:
    # the picture equals a full draw of the same figure, and nothing of one result stays in the next.
    import dataclasses

    from PIL import Image

    from cosy_lite.eval.command import RecallFigure

    r = _evaluate(root, _gt_estimates())
    s = r.scores
    worse = dataclasses.replace(r, scores=dataclasses.replace(s, recall_mssd=s.recall_mssd * 0.5,
                                                              recall_vsd=s.recall_vsd * 0.3))
    figure = RecallFigure(s.mspd_thresholds_px)
    pictures = []
    for k, result in enumerate((r, worse, r)):
        figure.save(result, tmp_path / f"{k}.png")
        pictures.append(np.asarray(Image.open(tmp_path / f"{k}.png")))
    assert pictures[0].shape == (420, 1500, 4)
    assert np.array_equal(pictures[0], pictures[2]) and not np.array_equal(pictures[0], pictures[1])
    figure.canvas.draw()  # everything again, in matplotlib's order, with the last result's curves and titles
    assert np.array_equal(np.asarray(figure.canvas.buffer_rgba()), pictures[2])
    with pytest.raises(ValueError, match="MSPD thresholds"):
        RecallFigure(s.mspd_thresholds_px * 2).save(r, tmp_path / "x.png")

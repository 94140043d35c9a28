"""BOP22 detection JSON (write, read, reject), oracle detections and COCO detection AP."""

from __future__ import annotations

import json
import math

import bop_fixtures as fx
import cv2
import numpy as np
import pytest
import torch

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.detections import (
    Detections,
    oracle_detections,
    read_detections_json,
    rle_to_mask,
    write_detections_json,
)
from cosy_lite.errors import BopFormatError
from cosy_lite.eval.detection import coco_ground_truth, evaluate_detections, evaluate_detections_file


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> BopDataset:
    return BopDataset(fx.write_tiny_bop(tmp_path_factory.mktemp("bop")))


def _records(dataset: BopDataset):
    return list(dataset.images(fx.SPLIT))


def _oracle(dataset: BopDataset) -> dict[tuple[int, int], Detections]:
    return {(r.scene_id, r.im_id): oracle_detections(dataset, r) for r in _records(dataset)}


def test_oracle_detections_are_the_visible_gt(dataset):
    rec = dataset.image(fx.SPLIT, fx.SCENE_ID, 1)
    det = oracle_detections(dataset, rec)
    assert det.obj_ids.tolist() == [1, 1, 2] and det.scores.tolist() == [1.0, 1.0, 1.0]
    x, y, w, h = rec.gt_info[2].bbox_visib
    assert det.boxes[2].tolist() == [x, y, x + w, y + h]
    assert det.masks.shape == (3, fx.HEIGHT, fx.WIDTH) and det.masks.dtype == torch.bool
    assert int(det.masks[2].sum()) == w * h and bool(det.masks[2, y, x]) and not det.masks[2, y - 1, x]
    assert oracle_detections(dataset, rec, with_masks=False).masks is None


def test_write_read_round_trip(dataset, tmp_path):
    dets = _oracle(dataset)
    extra = Detections(torch.tensor([[10.25, 20.5, 40.75, 80.0], [1.0, 2.0, 3.0, 4.0]]), torch.tensor([2, 1]),
                       torch.tensor([0.25, 0.875]), torch.zeros(2, fx.HEIGHT, fx.WIDTH, dtype=torch.bool), time_s=0.125)
    extra.masks[0, 20:80, 10:40] = True
    extra.masks[1, 2:4, 1:3] = True
    dets[(3, 7)] = extra
    path = tmp_path / "cosylite_tiny-test.json"
    write_detections_json(path, dets)
    back = read_detections_json(path, valid_obj_ids=dataset.obj_ids, with_masks=True)
    assert sorted(back) == sorted(dets)
    for key, d in dets.items():
        order = torch.argsort(-d.scores, stable=True)  # the reader sorts by decreasing score
        b = back[key]
        assert torch.equal(b.obj_ids, d.obj_ids[order]) and torch.equal(b.scores, d.scores[order])
        assert torch.allclose(b.boxes, d.boxes[order], atol=1e-6)
        assert torch.equal(b.masks, d.masks[order])
        assert b.time_s == d.time_s
    assert back[(3, 7)].obj_ids.tolist() == [1, 2] and back[(3, 7)].time_s == 0.125
    assert read_detections_json(path)[(3, 7)].masks is None  # masks only when asked


def test_file_is_valid_bop22_coco_results(dataset, tmp_path):
    from pycocotools.coco import COCO

    path = tmp_path / "cosylite_tiny-test.json"
    write_detections_json(path, _oracle(dataset))
    entries = json.loads(path.read_text())
    assert len(entries) == 5
    for e in entries:  # the checks of bop_toolkit inout.check_coco_results (bop22, segm)
        assert set(e) == {"scene_id", "image_id", "category_id", "score", "bbox", "segmentation", "time"}
        assert all(isinstance(e[k], int) for k in ("scene_id", "image_id", "category_id"))
        assert isinstance(e["score"], float) and isinstance(e["time"], float)
        assert isinstance(e["bbox"], list) and len(e["bbox"]) == 4
        assert isinstance(e["segmentation"]["counts"], str) and e["segmentation"]["size"] == [fx.HEIGHT, fx.WIDTH]
    gt, index = coco_ground_truth(dataset, _records(dataset))
    coco = COCO()
    coco.dataset = gt
    coco.createIndex()
    for e in entries:
        e["image_id"] = index[(e["scene_id"], e["image_id"])]
    res = coco.loadRes(entries)  # pycocotools accepts the file's entries
    assert len(res.anns) == 5
    first = res.anns[1]
    x, y, w, h = first["bbox"]
    assert res.annToMask(first).sum() == w * h


def _valid_entry() -> dict:
    return {"scene_id": 0, "image_id": 1, "category_id": 2, "score": 0.5, "bbox": [1.0, 2.0, 30.0, 40.0],
            "segmentation": {"size": [4, 3], "counts": [2, 3, 7]}, "time": 0.1}


MALFORMED = [  # (change to the second entry, field named by the error)
    (lambda e: e.pop("score"), "[1].score"),
    (lambda e: e.pop("scene_id"), "[1].scene_id"),
    (lambda e: e.update(score="high"), "[1].score"),
    (lambda e: e.update(score=float("nan")), "[1].score"),
    (lambda e: e.update(image_id=1.5), "[1].image_id"),
    (lambda e: e.update(category_id=99), "[1].category_id"),
    (lambda e: e.update(category_id="2"), "[1].category_id"),
    (lambda e: e.update(bbox=[1.0, 2.0, 3.0]), "[1].bbox"),
    (lambda e: e.update(bbox=[1.0, 2.0, -3.0, 4.0]), "[1].bbox"),
    (lambda e: e.update(segmentation={"counts": "abc"}), "[1].segmentation"),
    (lambda e: e.update(segmentation={"size": [4, 3], "counts": [2, 3]}), "[1].segmentation.counts"),
    (lambda e: e.update(time="fast"), "[1].time"),
]


@pytest.mark.parametrize("change,field", MALFORMED, ids=[f for _, f in MALFORMED])
def test_malformed_entries_name_the_field(tmp_path, change, field):
    bad = _valid_entry()
    change(bad)
    path = tmp_path / "dets.json"
    path.write_text(json.dumps([_valid_entry(), bad]))
    with pytest.raises(BopFormatError) as err:
        read_detections_json(path, valid_obj_ids=[1, 2])
    assert err.value.field == field and err.value.path == str(path)


def test_valid_uncompressed_entry_and_bad_files(tmp_path):
    path = tmp_path / "dets.json"
    path.write_text(json.dumps([_valid_entry()]))
    det = read_detections_json(path, valid_obj_ids=[2], with_masks=True)[(0, 1)]
    assert det.boxes.tolist() == [[1.0, 2.0, 31.0, 42.0]]
    assert det.masks[0].T.flatten().tolist() == [False] * 2 + [True] * 3 + [False] * 7  # column-major runs
    seg_only = {k: v for k, v in _valid_entry().items() if k != "bbox"}
    path.write_text(json.dumps([seg_only]))
    assert read_detections_json(path)[(0, 1)].boxes.tolist() == [[0.0, 0.0, 2.0, 4.0]]  # box of the mask
    path.write_text(json.dumps({"0": []}))
    with pytest.raises(BopFormatError, match="JSON list"):
        read_detections_json(path)
    path.write_text("[{")
    with pytest.raises(BopFormatError, match="malformed JSON"):
        read_detections_json(path)
    with pytest.raises(BopFormatError, match="not found"):
        read_detections_json(tmp_path / "missing.json")


def test_rle_helpers_agree():
    m = np.zeros((5, 7), bool)
    m[1:4, 2:6] = True
    assert (rle_to_mask({"size": [5, 7], "counts": [11, 3, 2, 3, 2, 3, 2, 3, 6]}) == m).all()


def test_gt_as_detections_scores_one(dataset, tmp_path):
    scores = evaluate_detections(dataset, _records(dataset), _oracle(dataset))
    assert [scores.ap, scores.ap50, scores.ap75, scores.mask_ap, scores.mask_ap50] == pytest.approx([1.0] * 5)
    assert (scores.n_images, scores.n_gt, scores.n_detections) == (2, 5, 5)
    path = tmp_path / "oracle_tiny-test.json"
    write_detections_json(path, _oracle(dataset))
    assert evaluate_detections_file(dataset, _records(dataset), path).mask_ap == pytest.approx(1.0)
    boxes_only = {k: Detections(d.boxes, d.obj_ids, d.scores) for k, d in _oracle(dataset).items()}
    s = evaluate_detections(dataset, _records(dataset), boxes_only)
    assert s.ap == pytest.approx(1.0) and math.isnan(s.mask_ap)
    assert evaluate_detections(dataset, _records(dataset), {}).ap == 0.0


def test_shifted_box_gives_the_known_ap(dataset):
    rec = dataset.image(fx.SPLIT, fx.SCENE_ID, 0)  # obj 1 and obj 2, one instance each
    det = oracle_detections(dataset, rec)
    x, y, w, h = rec.gt_info[0].bbox_visib
    dx = round(0.19 * w)
    iou = (w - dx) / (w + dx)
    assert 0.65 < iou < 0.70  # passes IoU thresholds 0.50, 0.55, 0.60, 0.65: AP 4/10 for obj 1
    det.boxes[0, [0, 2]] += dx
    det.masks[0] = torch.roll(det.masks[0], dx, dims=1)
    assert not det.masks[0, :, :dx].any()  # no wrap-around: the mask IoU is the same
    s = evaluate_detections(dataset, [rec], {(rec.scene_id, rec.im_id): det})
    assert [s.ap, s.ap50, s.ap75] == pytest.approx([(1.0 + 0.4) / 2, 1.0, 0.5])
    assert [s.mask_ap, s.mask_ap50] == pytest.approx([s.ap, 1.0])


# ----------------------------------------------------------------------------- BOP 2D tasks (eval_bop22_coco.py)


def _gt_boxes(dataset, rec) -> dict[int, list[float]]:
    """obj_id -> its amodal GT box (x, y, w, h) in ``rec`` (one instance per object there)."""
    gt, _ = coco_ground_truth(dataset, [rec], "amodal")
    return {a["category_id"]: a["bbox"] for a in gt["annotations"]}


def _entry(rec, obj_id: int, box, score: float) -> dict:
    return {"scene_id": rec.scene_id, "image_id": rec.im_id, "category_id": obj_id, "score": score,
            "bbox": [float(v) for v in box], "time": 0.25}


def _scores(dataset, rec, entries, tmp_path, name="x") -> dict:
    from cosy_lite.eval.detection import bop22_coco_scores

    path = tmp_path / f"{name}_tiny-test.json"
    path.write_text(json.dumps(entries))
    return bop22_coco_scores(dataset, [rec], path, "bbox")


def test_2d_detection_ap_by_hand(dataset, tmp_path):
    """Image 0 has obj 1 and obj 2 once each; true positives are their GT boxes (IoU 1), false
    positives a 20 px box in a corner (IoU 0). AP is the mean over the two objects of COCO's
    101-point interpolated precision, the same at every IoU threshold here."""
    rec = dataset.image(fx.SPLIT, fx.SCENE_ID, 0)
    box = _gt_boxes(dataset, rec)
    assert sorted(box) == [1, 2]
    tp = [_entry(rec, 1, box[1], 0.5), _entry(rec, 2, box[2], 0.5)]
    fp = _entry(rec, 1, [0, 0, 20, 20], 0.9)
    s = _scores(dataset, rec, tp, tmp_path)
    assert (s["AP"], s["AP50"], s["AR100"], s["average_time_per_image"]) == pytest.approx((1.0, 1.0, 1.0, 0.25))
    # a false positive of obj 1 scored above its true positive: precision 1/2 at recall 1 -> (0.5 + 1) / 2
    assert _scores(dataset, rec, [fp] + tp, tmp_path)["AP"] == pytest.approx(0.75)
    # ... scored below: it comes after the recall is complete and costs nothing
    assert _scores(dataset, rec, tp + [dict(fp, score=0.1)], tmp_path)["AP"] == pytest.approx(1.0)
    # a tie keeps the file's order (pycocotools' stable sort of what the toolkit gives it)
    assert _scores(dataset, rec, [dict(fp, score=0.5)] + tp, tmp_path)["AP"] == pytest.approx(0.75)
    assert _scores(dataset, rec, tp + [dict(fp, score=0.5)], tmp_path)["AP"] == pytest.approx(1.0)
    # only the 100 best-scored detections of an image count: the true positive of obj 1 ranked 100th
    # gives precision 1/100 at recall 1; ranked 101st it is not seen
    fps = [dict(fp, score=0.9 - 1e-4 * k) for k in range(100)]
    assert _scores(dataset, rec, fps[:99] + tp, tmp_path)["AP"] == pytest.approx((0.01 + 1.0) / 2)
    assert _scores(dataset, rec, fps + tp, tmp_path)["AP"] == pytest.approx((0.0 + 1.0) / 2)
    # a missed object: obj 2 not detected -> its AP 0
    assert _scores(dataset, rec, tp[:1], tmp_path)["AP"] == pytest.approx(0.5)
    # entries of other images are not scored; no entry left: -1, as the toolkit
    other = dict(tp[0], image_id=rec.im_id + 100)
    s = _scores(dataset, rec, [other], tmp_path)
    assert s["AP"] == -1.0 and s["average_time_per_image"] == -1.0


# Image 0 rewritten (toolkit semantics of eval_bop22_coco.py, each number checked against the official
# toolkit with its pycocotools fork): obj 1 cut by the left border and partly occluded, obj 2 hidden.
CUT_FULL = (0, 100, 100, 80)  # x, y, w, h of obj 1's full mask: columns 0..99, rows 100..179
CUT_VISIB = (40, 100, 60, 60)  # its visible part: 3,600 px (COCO "medium"), visib_fract 0.45
CUT_BBOX_OBJ = [-50, 90, 160, 100]  # its projected box, beyond the border and looser than the mask
HIDDEN_FULL, HIDDEN_VISIB = (400, 300, 50, 50), (400, 300, 10, 10)  # obj 2: 100 of 2,500 px visible


def _write_masks(root, im_id: int, gt_idx: int, full, visib) -> None:
    for sub, (x, y, w, h) in (("mask", full), ("mask_visib", visib)):
        mask = np.zeros((fx.HEIGHT, fx.WIDTH), np.uint8)
        mask[y:y + h, x:x + w] = 255
        cv2.imwrite(str(fx.scene_dir(root) / sub / f"{im_id:06d}_{gt_idx:06d}.png"), mask)


def border_and_hidden_dataset(parent) -> BopDataset:
    """The tiny dataset with image 0 as above; ``gt_info`` as the toolkit's ``calc_gt_info.py`` writes
    it (``bbox_visib`` one pixel short of the mask's extent)."""
    root = fx.write_tiny_bop(parent)
    _write_masks(root, 0, 0, CUT_FULL, CUT_VISIB)
    _write_masks(root, 0, 1, HIDDEN_FULL, HIDDEN_VISIB)
    path = fx.scene_dir(root) / "scene_gt_info.json"
    info = json.loads(path.read_text())
    for k, (full, visib, bbox_obj) in enumerate(((CUT_FULL, CUT_VISIB, CUT_BBOX_OBJ),
                                                 (HIDDEN_FULL, HIDDEN_VISIB, list(HIDDEN_FULL)))):
        n_all, n_vis = full[2] * full[3], visib[2] * visib[3]
        info["0"][k].update(bbox_obj=bbox_obj, bbox_visib=[visib[0], visib[1], visib[2] - 1, visib[3] - 1],
                            px_count_all=n_all, px_count_valid=n_all, px_count_visib=n_vis, visib_fract=n_vis / n_all)
    path.write_text(json.dumps(info))
    return BopDataset(root)


def _square_rle(x: int, y: int, w: int, h: int) -> dict:
    from cosy_lite.bop.detections import mask_to_rle

    mask = np.zeros((fx.HEIGHT, fx.WIDTH), bool)
    mask[y:y + h, x:x + w] = True
    return mask_to_rle(mask)


def hand_cases() -> list[tuple[str, str, list[dict], dict[str, float]]]:
    """(ann_type, bbox_type, results of image 0, expected scores) on :func:`border_and_hidden_dataset`."""
    def det(obj_id, box, score, **extra):
        return {"scene_id": fx.SCENE_ID, "image_id": 0, "category_id": obj_id, "score": score,
                "bbox": [float(v) for v in box], "time": 0.5, **extra}

    x, y, w, h = CUT_VISIB
    return [
        # the amodal GT box is the full mask's: IoU 1 (the clipped bbox_obj would give 0.73: AP 0.5);
        # obj 2 has only an ignored GT instance: its category is not scored (AP 1, not 0.5)
        ("bbox", "amodal", [det(1, CUT_FULL, 0.9)], {"AP": 1.0, "AR100": 1.0, "AP_medium": 1.0}),
        ("bbox", "amodal", [det(1, [0, 90, 110, 100], 0.9)], {"AP": 0.5, "AP50": 1.0, "AP75": 0.0}),
        # a detection on the ignored instance is neither a true nor a false positive
        ("bbox", "amodal", [det(2, HIDDEN_FULL, 0.95), det(1, CUT_FULL, 0.9), det(2, (600, 0, 20, 20), 0.99)],
         {"AP": 1.0, "AR1": 1.0}),
        # modal: the visible mask's box (gt_info's bbox_visib is a pixel short); a box 6 px narrower
        # has IoU 0.9: matched at 9 of the 10 thresholds
        ("bbox", "modal", [det(1, CUT_VISIB, 0.9)], {"AP": 1.0}),
        ("bbox", "modal", [det(1, (x, y, w - 6, h), 0.9)], {"AP": 0.9, "AP75": 1.0}),
        # segmentation with boxes: the box's area (100 px, "small") decides the size class of the
        # false positive whose mask has 2,500 px ("medium"): it costs AP but not AP_medium
        ("segm", "amodal", [det(1, CUT_VISIB, 0.5, segmentation=_square_rle(*CUT_VISIB)),
                            det(1, (600, 0, 10, 10), 0.9, segmentation=_square_rle(300, 20, 50, 50))],
         {"AP": 0.5, "AP_medium": 1.0, "AP_small": -1.0, "AR100": 1.0}),
        # ... without boxes the mask's area decides: AP_medium 0.5
        ("segm", "amodal", [{k: v for k, v in d.items() if k != "bbox"} for d in (
            det(1, CUT_VISIB, 0.5, segmentation=_square_rle(*CUT_VISIB)),
            det(1, (600, 0, 10, 10), 0.9, segmentation=_square_rle(300, 20, 50, 50)))],
         {"AP": 0.5, "AP_medium": 0.5}),
    ]


def test_2d_ground_truth_boxes_are_the_boxes_of_the_masks(tmp_path):
    ds = border_and_hidden_dataset(tmp_path)
    rec = ds.image(fx.SPLIT, fx.SCENE_ID, 0)
    amodal, _ = coco_ground_truth(ds, [rec], "amodal")
    modal, _ = coco_ground_truth(ds, [rec], "modal")
    assert [a["bbox"] for a in amodal["annotations"]] == [list(map(float, CUT_FULL)), list(map(float, HIDDEN_FULL))]
    assert [a["bbox"] for a in modal["annotations"]] == [list(map(float, CUT_VISIB)), list(map(float, HIDDEN_VISIB))]
    assert [a["area"] for a in amodal["annotations"]] == [3600, 100]  # visible pixels, whatever the box
    assert [a["ignore"] for a in amodal["annotations"]] == [0, 1]  # visib_fract 0.45, 0.04


@pytest.mark.parametrize("case", range(7))
def test_2d_scores_by_hand_as_the_toolkit(tmp_path, case):
    from cosy_lite.eval.detection import bop22_coco_scores

    ds = border_and_hidden_dataset(tmp_path)
    ann_type, bbox_type, results, expected = hand_cases()[case]
    path = tmp_path / "x_tiny-test.json"
    path.write_text(json.dumps(results))
    scores = bop22_coco_scores(ds, [ds.image(fx.SPLIT, fx.SCENE_ID, 0)], path, ann_type, bbox_type)
    assert {k: scores[k] for k in expected} == pytest.approx(expected)


def test_cosy_lite_eval_2d_tasks_write_the_toolkits_files(dataset, tmp_path, capsys):
    from cosy_lite.cli import main
    from cosy_lite.eval.detection import COCO_KEYS

    path = tmp_path / "oracle_tiny-test.json"
    write_detections_json(path, _oracle(dataset))
    for task, name in (("2d-detection", "scores_bop22_coco_bbox"), ("2d-segmentation", "scores_bop22_coco_segm")):
        assert main(["eval", "--dataset", str(dataset.root), "--results", str(path), "--task", task,
                     "--out", str(tmp_path / "ev")]) == 0
        scores = json.loads((tmp_path / "ev" / f"{name}.json").read_text())
        assert list(scores) == [*COCO_KEYS, "average_time_per_image"]
        assert scores["AP"] == pytest.approx(1.0) and scores["AR100"] == pytest.approx(1.0)
    assert main(["eval", "--dataset", str(dataset.root), "--results", str(path), "--task", "2d-detection",
                 "--bbox-type", "modal", "--out", str(tmp_path / "ev")]) == 0
    assert json.loads((tmp_path / "ev" / "scores_bop22_coco_bbox_modal.json").read_text())["AP"] == pytest.approx(1.0)
    capsys.readouterr()
    assert main(["eval", "--dataset", str(dataset.root), "--results", str(tmp_path / "none.json"),
                 "--task", "2d-detection"]) == 1
    assert "results file not found" in capsys.readouterr().out
    bad = tmp_path / "bad_tiny-test.json"
    bad.write_text(json.dumps([{"scene_id": 0, "image_id": 0, "category_id": 1, "score": "high", "bbox": [0, 0, 1, 1]}]))
    assert main(["eval", "--dataset", str(dataset.root), "--results", str(bad), "--task", "2d-detection"]) != 0
    text = "".join(capsys.readouterr())
    assert f"{bad}" in text and "[0].score" in text and "Traceback" not in text

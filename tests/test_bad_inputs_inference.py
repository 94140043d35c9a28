"""Bad detections at inference: a box of zero width/height (or NaN) is skipped with a warning, never
a pose hundreds of metres away; detection files of another split, masks of another size, broken
entries and missing files are one error naming the file and the field. An image over the pixel
limit (``cosy-lite predict``, ``infer.py``) is refused from its header, before it is decoded."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from bop_fixtures import forbid_decoding, scene_dir, write_huge_png, write_tiny_bop
from torch import nn

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.detections import Detections, degenerate_boxes
from cosy_lite.bop.results import read_results_csv
from cosy_lite.errors import BopFormatError
from cosy_lite.inference.bop_run import run_on_split
from cosy_lite.inference.object_meshes import ObjectMeshes, objects_and_renderer
from cosy_lite.inference.predictor import Predictor
from cosy_lite.inference.settings import InferenceConfig
from cosy_lite.weights.loaders import PoseModel

CROP = (60, 80)
MAX_DEPTH_M = 10.0  # the fixture's objects are 0.7-0.9 m away


class _Still(nn.Module):
    """A pose network whose update is the identity (zeros, as an untrained head)."""

    def forward(self, x):
        return torch.zeros(len(x), 9)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> BopDataset:
    return BopDataset(write_tiny_bop(tmp_path_factory.mktemp("bop")))


@pytest.fixture(scope="module")
def predictor(dataset) -> Predictor:
    objects, renderer, _ = objects_and_renderer(ObjectMeshes(dataset.models_dir), [1, 2], 200, icp=False)
    return Predictor(PoseModel(_Still(), "coarse", CROP, [1, 2]), None, objects, renderer,
                     config=InferenceConfig(n_refiner_iterations=0))


def _det(boxes: list[list[float]], obj_ids: list[int]) -> Detections:
    return Detections(torch.tensor(boxes, dtype=torch.float32), torch.tensor(obj_ids),
                      torch.linspace(0.9, 0.5, len(obj_ids)))


GOOD = [200.0, 150.0, 260.0, 230.0]


@pytest.mark.parametrize("bad", [[100.0, 100.0, 100.0, 150.0], [100.0, 100.0, 180.0, 100.0],
                                 [100.0, 100.0, 100.5, 150.0], [float("nan"), 100.0, 120.0, 150.0],
                                 [100.0, 100.0, 60.0, 150.0]],
                         ids=["zero-width", "zero-height", "half-pixel", "nan", "inverted"])
def test_degenerate_box_is_skipped_with_a_warning(dataset, predictor, bad):
    rec = next(dataset.images("test"))
    det = _det([bad, GOOD], [1, 2])
    assert degenerate_boxes(det).tolist() == [True, False]
    with pytest.warns(RuntimeWarning, match=r"1 detection\(s\) with a box side under 1.0 px .* skipped"):
        est = predictor.predict(dataset.load_rgb(rec), rec.camera.K, detections=det)
    assert est.obj_ids.tolist() == [2] and bool(est.valid.all())
    assert float(est.TCO[0, 2, 3]) < MAX_DEPTH_M


def test_one_pixel_box_is_still_estimated(dataset, predictor):
    rec = next(dataset.images("test"))
    est = predictor.predict(dataset.load_rgb(rec), rec.camera.K, detections=_det([[100.0, 100.0, 101.0, 101.0]], [1]))
    assert len(est) == 1


def _detections_file(path: Path, entries: list[dict]) -> Path:
    path.write_text(json.dumps(entries))
    return path


def _entry(scene_id=0, image_id=0, category_id=1, bbox=(180.0, 120.0, 90.0, 70.0), **extra) -> dict:
    return {"scene_id": scene_id, "image_id": image_id, "category_id": category_id, "score": 0.8,
            "bbox": list(bbox), "time": 0.1, **extra}


def test_zero_size_box_in_a_detections_file_is_skipped_and_reported(dataset, predictor, tmp_path):
    path = _detections_file(tmp_path / "det_tiny-test.json", [
        _entry(bbox=(300.0, 200.0, 0.0, 40.0)), _entry(category_id=2), _entry(image_id=1)])
    summary = run_on_split(predictor, dataset, tmp_path, detections=path, progress=False)
    assert summary.n_degenerate == 1 and summary.ok
    assert any("1 detections with a box side under 1.0 px" in line for line in summary.lines())
    rows = read_results_csv(summary.csv_path)
    assert sorted((e.im_id, e.obj_id) for e in rows) == [(0, 2), (1, 1)]
    assert max(e.TCO[2, 3] for e in rows) < MAX_DEPTH_M


@pytest.mark.parametrize("entries, fld, words", [
    ([_entry(scene_id=7), _entry(scene_id=7, image_id=1)], "scene_id/image_id", "none of its 2 images"),
    ([_entry(bbox=(10.0, 10.0, -5.0, 20.0))], "[0].bbox", "width and height must be >= 0"),
    ([_entry(category_id=9)], "[0].category_id", "unknown obj_id 9"),
    ([_entry(score=float("nan"))], "[0].score", "finite number"),
    ([_entry(image_id="0")], "[0].image_id", "expected an integer"),
    ({"scene_id": 0}, "", "expected a JSON list"),
    ([_entry(segmentation={"size": [20000, 20000], "counts": "0"})], "[0].segmentation.size",
     "20000 x 20000 pixels: more than the limit of 40 MP"),
], ids=["other-split", "negative-width", "unknown-object", "nan-score", "string-id", "not-a-list", "huge-mask"])
def test_broken_detections_file_names_the_field(dataset, predictor, tmp_path, entries, fld, words):
    path = _detections_file(tmp_path / "det.json", entries)
    with pytest.raises(BopFormatError) as e:
        run_on_split(predictor, dataset, tmp_path, detections=path, progress=False)
    assert e.value.path == str(path) and e.value.field == fld and words in e.value.problem, str(e.value)


def test_masks_of_another_size_are_refused(dataset, predictor, tmp_path):
    from cosy_lite.bop.detections import mask_to_rle

    mask = np.zeros((240, 320), bool)
    mask[50:90, 60:120] = True
    path = _detections_file(tmp_path / "det.json", [_entry(segmentation=mask_to_rle(mask))])
    with_icp = Predictor(predictor.coarse, None, predictor.objects, predictor.renderer,
                         config=InferenceConfig(n_refiner_iterations=0, icp=True))
    with pytest.raises(BopFormatError, match=r"det\.json \[segmentation\.size\]: masks of scene 0 image 0 are \[240, "):
        run_on_split(with_icp, dataset, tmp_path, detections=path, progress=False)


def test_missing_detections_file(dataset, predictor, tmp_path):
    with pytest.raises(BopFormatError, match=r"nothere\.json \[--detections\]: detections file not found"):
        run_on_split(predictor, dataset, tmp_path, detections=tmp_path / "nothere.json", progress=False)


# ----------------------------------------------------------------------------- images over the pixel limit


@pytest.fixture(scope="module")
def huge_png(tmp_path_factory) -> Path:
    """20000 x 20000 pixels in a 50 kB file (decoded: 1.2 GB as RGB)."""
    return write_huge_png(tmp_path_factory.mktemp("huge") / "huge.png")


def _one_error_line(err: str, prog: str, path: Path) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"{prog}: error: {path} [size]: 20000 x 20000 pixels (400 MP): more than the limit "
                               "of 40 MP"), lines[0]


@pytest.mark.parametrize("which", ["rgb", "depth"])
def test_predict_refuses_an_image_over_the_pixel_limit_from_its_header(dataset, huge_png, tmp_path, capsys,
                                                                       monkeypatch, which):
    from cosy_lite.cli import main

    rec = next(dataset.images("test"))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"cam_K": rec.camera.K.reshape(-1).tolist()}))  # no width/height to compare with
    images = {"rgb": huge_png, "depth": rec.depth_path} if which == "rgb" else {"rgb": rec.rgb_path, "depth": huge_png}
    forbid_decoding(monkeypatch, huge_png)
    rc = main(["predict", "--rgb", str(images["rgb"]), "--depth", str(images["depth"]), "--camera", str(camera),
               "--meshes", str(dataset.root), "--coarse", str(tmp_path / "c.pt"), "--detections",
               str(tmp_path / "d.json"), "--out", str(tmp_path / "out")])
    assert rc == 2
    _one_error_line(capsys.readouterr().err, "cosy-lite predict", huge_png)


@pytest.mark.parametrize("which", ["rgb", "depth"])
def test_infer_refuses_a_dataset_image_over_the_pixel_limit(huge_png, tmp_path, capsys, monkeypatch, which):
    from test_inference import _save_pose_ckpt

    import infer

    root = write_tiny_bop(tmp_path)
    image = scene_dir(root) / which / "000000.png"
    shutil.copyfile(huge_png, image)
    forbid_decoding(monkeypatch, image)
    coarse = _save_pose_ckpt(tmp_path / "coarse.pt", "coarse", obj_ids=[1, 2])
    rc = infer.main(["--dataset", str(root), "--coarse", str(coarse), "--detections", "oracle", "--n-refiner-iters",
                     "0", "--out", str(tmp_path / "out"), "--no-progress", *(["--icp"] if which == "depth" else [])])
    assert rc == 2
    _one_error_line(capsys.readouterr().err, "infer.py", image)

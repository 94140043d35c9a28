"""check_dataset on the tiny fixture: clean -> no problem; each corruption -> an error naming the
file and the field; the check-dataset command's exit codes."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from bop_fixtures import edit_json, scene_dir, write_models, write_tiny_bop

from cosy_lite.bop import command_check_dataset
from cosy_lite.bop.validate import Problem, check_dataset


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return write_tiny_bop(tmp_path)


def _errors(problems: list[Problem]) -> list[tuple[str, str]]:
    """(path relative to the dataset folder's parent, field) of every error."""
    return [(p.path, p.field) for p in problems if p.severity == "error"]


def _expect(root: Path, problems: list[Problem], rel: str, fld: str, words: str = "") -> Problem:
    path = str(root / rel)
    hits = [p for p in problems if p.severity == "error" and p.path == path and p.field == fld]
    assert hits, f"no error for {rel} [{fld}] in:\n" + "\n".join(map(str, problems))
    assert words in hits[0].message, hits[0].message
    return hits[0]


SCENE = "test/000000"


def test_clean_fixture_has_no_problem(root: Path):
    assert check_dataset(root) == []
    assert check_dataset(root, "tiny", ["test"], check_images=False) == []


def test_problem_is_one_line():
    p = Problem("a/b.json", "0.cam_K", "bad\nvery bad", "warning")
    assert str(p) == "WARNING a/b.json [0.cam_K]: bad very bad"
    with pytest.raises(ValueError, match="severity"):
        Problem("a", "b", "c", "fatal")


# ----------------------------------------------------------------------------- scene files


@pytest.mark.parametrize("file, change, fld, words", [
    ("scene_camera.json", lambda d: d["1"].pop("cam_K"), "1.cam_K", "missing"),
    ("scene_camera.json", lambda d: d["0"]["cam_K"].pop(), "0.cam_K", "expected 9 numbers, got 8"),
    ("scene_camera.json", lambda d: d.update(first=d.pop("0")), "first", "integer"),
    ("scene_gt.json", lambda d: d["1"][1]["cam_R_m2c"].__setitem__(4, 0.2), "1[1].cam_R_m2c", "rotation"),
    ("scene_gt.json", lambda d: d["0"][0]["cam_t_m2c"].__setitem__(0, float("nan")), "0[0].cam_t_m2c", "NaN"),
    ("scene_gt.json", lambda d: d["0"][1].update(cam_t_m2c=[0.1, 0.04, 0.8]), "0[1].cam_t_m2c", "metres"),
    ("scene_gt.json", lambda d: d["1"][2].update(obj_id=7), "1[2].obj_id", "not in models_info"),
    ("scene_gt_info.json", lambda d: d["1"].pop(), "1", "2 entries, but scene_gt.json has 3"),
    ("scene_gt_info.json", lambda d: d.pop("1"), "image ids", "image ids 1 of scene_camera.json are missing"),
], ids=["missing-cam_K", "cam_K-8-numbers", "non-integer-key", "non-orthonormal-R", "nan-t", "t-in-metres",
        "obj_id-not-in-models_info", "gt-info-count", "image-ids-differ"])
def test_scene_file_problem(root: Path, file: str, change, fld: str, words: str):
    edit_json(scene_dir(root) / file, change)
    _expect(root, check_dataset(root), f"{SCENE}/{file}", fld, words)


def test_missing_scene_file(root: Path):
    (scene_dir(root) / "scene_gt_info.json").unlink()
    _expect(root, check_dataset(root), f"{SCENE}/scene_gt_info.json", "", "not found")


def test_malformed_json(root: Path):
    path = scene_dir(root) / "scene_camera.json"
    path.write_text(path.read_text().replace(":", "", 1))
    problems = check_dataset(root)
    _expect(root, problems, f"{SCENE}/scene_camera.json", "", "malformed JSON")
    assert _errors(problems) == [(str(path), "")]  # the other checks go on without it


def test_withheld_gt_is_a_warning(root: Path):
    (scene_dir(root) / "scene_gt.json").unlink()
    (scene_dir(root) / "scene_gt_info.json").unlink()
    problems = check_dataset(root)
    assert [p.severity for p in problems] == ["warning"] and problems[0].path == str(scene_dir(root))


# ----------------------------------------------------------------------------- models


def test_models_info_diameter_in_metres(root: Path):
    edit_json(root / "models" / "models_info.json", lambda d: d["1"].update(diameter=d["1"]["diameter"] / 1000))
    problems = check_dataset(root)
    _expect(root, problems, "models/models_info.json", "1.diameter", "metres")
    mix = _expect(root, problems, "models/obj_000001.ply", "vertex", "mm/m mix-up")
    assert str(root / "models" / "models_info.json") in mix.message  # names both files
    assert not [p for p in problems if "obj_000002" in p.path]


def test_model_file_in_metres(root: Path):
    write_models(root, scale=1e-3, obj_ids=(2,))
    problems = check_dataset(root)
    for folder in ("models", "models_eval"):
        _expect(root, problems, f"{folder}/obj_000002.ply", "vertex", "models_info.json")
    assert len(_errors(problems)) == 2


def test_missing_eval_model(root: Path):
    (root / "models_eval" / "obj_000001.ply").unlink()
    problems = check_dataset(root)
    _expect(root, problems, "models_eval/obj_000001.ply", "", "not found")
    assert len(_errors(problems)) == 1


def test_inconsistent_diameter_is_a_warning(root: Path):
    edit_json(root / "models" / "models_info.json", lambda d: d["1"].update(diameter=300.0))
    problems = check_dataset(root)
    assert [(Path(p.path).name, p.field, p.severity) for p in problems] == [
        ("models_info.json", "1.diameter", "warning"), ("models_info.json", "1.diameter", "warning")]


# ----------------------------------------------------------------------------- image files


def test_image_size_not_matching_params(root: Path):
    rgb = scene_dir(root) / "rgb" / "000001.png"
    cv2.imwrite(str(rgb), np.zeros((240, 320, 3), np.uint8))
    problems = check_dataset(root)
    _expect(root, problems, f"{SCENE}/rgb/000001.png", "size", "320x240 pixels, expected 640x480")
    assert len(_errors(problems)) == 1
    assert check_dataset(root, check_images=False) == []


def test_image_size_not_matching_camera(tmp_path: Path):
    root = write_tiny_bop(tmp_path, name="mydata")  # not in the parameter table: no im_size to compare with
    for sub, dtype in (("rgb", np.uint8), ("depth", np.uint16)):
        cv2.imwrite(str(scene_dir(root) / sub / "000000.png"), np.zeros((240, 300), dtype))
    problems = check_dataset(root)
    assert [p.field for p in problems if p.severity == "warning"] == ["name"]
    _expect(root, problems, f"{SCENE}/scene_camera.json", "0.cam_K", "principal point (313.0, 241.3) lies outside")
    cv2.imwrite(str(scene_dir(root) / "depth" / "000001.png"), np.zeros((480, 641), np.uint16))
    _expect(root, check_dataset(root), f"{SCENE}/depth/000001.png", "size", "641x480 pixels, but the rgb image is 640x480")


def test_missing_rgb_file(root: Path):
    (scene_dir(root) / "rgb" / "000001.png").unlink()
    problems = check_dataset(root)
    _expect(root, problems, f"{SCENE}/rgb/000001.png", "rgb", "image id 1")
    assert len(_errors(problems)) == 1


def test_missing_depth_folder(root: Path):
    shutil.rmtree(scene_dir(root) / "depth")
    assert _errors(check_dataset(root)) == [(str(scene_dir(root) / "depth"), "depth")]


def test_missing_mask_file(root: Path):
    (scene_dir(root) / "mask_visib" / "000001_000002.png").unlink()
    problems = check_dataset(root)
    _expect(root, problems, f"{SCENE}/mask_visib/000001_000002.png", "mask_visib", "GT instance 2 of image 1")
    assert len(_errors(problems)) == 1


def test_unreadable_image(root: Path):
    (scene_dir(root) / "rgb" / "000000.png").write_bytes(b"not a png")
    _expect(root, check_dataset(root), f"{SCENE}/rgb/000000.png", "", "cannot read the image header")


# ----------------------------------------------------------------------------- test targets


@pytest.mark.parametrize("change, fld, words", [
    (lambda d: d[2].update(im_id=5), "[2].im_id", "image 5 not in"),
    (lambda d: d[0].update(scene_id=3), "[0].scene_id", "scene 3 not found"),
    (lambda d: d[1].update(obj_id=8), "[1].obj_id", "obj_id 8 is not in models_info"),
    (lambda d: d[2].update(inst_count=3), "[2].inst_count", "3 instances of obj_id 1"),
], ids=["missing-image", "missing-scene", "unknown-object", "too-many-instances"])
def test_test_target_problem(root: Path, change, fld: str, words: str):
    edit_json(root / "test_targets_bop19.json", change)
    problems = check_dataset(root, splits=["test"])
    _expect(root, problems, "test_targets_bop19.json", fld, words)
    assert len(_errors(problems)) == 1


def test_test_targets_checked_when_test_split_not_selected(root: Path):
    (root / "train_pbr").mkdir()  # an empty split, selected alone
    edit_json(root / "test_targets_bop19.json", lambda d: d[2].update(im_id=5))
    problems = check_dataset(root, splits=["train_pbr"])
    assert _errors(problems) == [(str(root / "train_pbr"), ""), (str(root / "test_targets_bop19.json"), "[2].im_id")]


# ----------------------------------------------------------------------------- command


def _check_dataset_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    command_check_dataset.add_arguments(parser)
    return command_check_dataset.run(parser.parse_args(argv))


def test_command_check_dataset(root: Path, capsys):
    assert _check_dataset_cli([str(root), "--split", "test", "--no-images"]) == 0
    assert capsys.readouterr().out.strip() == f"OK {root}: 0 errors, 0 warnings"
    (scene_dir(root) / "mask" / "000000_000001.png").unlink()
    edit_json(scene_dir(root) / "scene_gt.json", lambda d: d["1"][0].update(obj_id=4))
    assert _check_dataset_cli([str(root), "--name", "tiny"]) == 1
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1] == f"FAILED {root}: 3 errors, 0 warnings"  # + the target now asking for 2 of obj 1
    assert all(line.startswith(f"ERROR {root}") for line in lines[:-1]) and len(lines) == 4
    assert "test_targets_bop19.json [[2].inst_count]" in lines[-2]

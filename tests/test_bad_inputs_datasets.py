"""Broken datasets against ``cosy-lite check-dataset`` and ``cosy-lite eval``: each corruption is an
error naming the file and the field (exit 1), eval refuses to score it (no scores.json, no
traceback); what the BOP toolkit reads (nested cam_K rows, 16-bit colour images) is accepted."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from bop_fixtures import GT, edit_json, forbid_decoding, scene_dir, write_huge_png, write_models, write_tiny_bop

from cosy_lite.bop import io
from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.results import PoseEstimate, write_results_csv
from cosy_lite.cli import main
from cosy_lite.errors import BopFormatError

# torchvision (imported by the inference modules) before any rendering: after Mesa has rendered,
# importing it crashes the process (see cosy_lite/inference/predictor.py).
from cosy_lite.inference.bop_run import run_on_split

SCENE = "test/000000"


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return write_tiny_bop(tmp_path)


def _gt_csv(root: Path) -> Path:
    """The GT poses as a results file (AR 1.0 on a sound dataset)."""
    ests = []
    for im_id, insts in GT.items():
        for obj_id, R, t in insts:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t / 1000.0
            ests.append(PoseEstimate(0, im_id, obj_id, 0.9, T, 0.1))
    csv = root.parent / "gt_tiny-test.csv"
    write_results_csv(csv, ests)
    return csv


def _cli(capsys, *argv: str) -> tuple[int, str]:
    rc = main(list(argv))
    captured = capsys.readouterr()
    return rc, captured.out + captured.err


def _eval(root: Path, capsys) -> tuple[int, str]:
    csv = _gt_csv(root)
    return _cli(capsys, "eval", "--dataset", str(root), "--results", str(csv), "--out", str(root.parent / "ev"),
                "--no-progress")


def _ply_text(vertices: np.ndarray, faces: np.ndarray | None) -> str:
    head = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
            "property float z"]
    if faces is not None:
        head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    triangles = [f"3 {a} {b} {c}" for a, b, c in (faces if faces is not None else [])]
    body = [" ".join(map(str, v)) for v in vertices] + triangles
    return "\n".join(head + ["end_header"] + body) + "\n"


def _box_ply(root: Path, obj_id: int, bad_face: bool = False, no_faces: bool = False) -> None:
    import trimesh

    box = trimesh.creation.box(extents=(100.0, 60.0, 40.0) if obj_id == 1 else (50.0, 50.0, 80.0))
    faces = np.array(box.faces)
    if bad_face:
        faces[3, 1] = 99
    text = _ply_text(np.asarray(box.vertices), None if no_faces else faces)
    (root / "models_eval" / f"obj_{obj_id:06d}.ply").write_text(text)


def _truncate_mesh(root: Path) -> None:
    p = root / "models_eval" / "obj_000001.ply"
    p.write_bytes(p.read_bytes()[:200])


def _rgb_depth(sub: str, im_id: int, array: np.ndarray):
    return lambda root: cv2.imwrite(str(scene_dir(root) / sub / f"{im_id:06d}.png"), array)


def _json(file: str, change):
    def apply(root: Path) -> None:
        path = root / file if not file.startswith("scene") else scene_dir(root) / file
        edit_json(path, change)
    return apply


def _raw(file: str, text: bytes):
    return lambda root: (scene_dir(root) / file).write_bytes(text)


def _replace_key(d: dict, old: str, new: str) -> None:
    d[new] = d.pop(old)


# (corruption, file relative to the dataset folder, field, words of the message)
CORRUPTIONS = {
    "depth-8-bit": (_rgb_depth("depth", 0, np.full((480, 640), 150, np.uint8)), f"{SCENE}/depth/000000.png",
                    "bit depth", "16-bit"),
    "depth-3-channels": (_rgb_depth("depth", 1, np.zeros((480, 640, 3), np.uint8)), f"{SCENE}/depth/000001.png",
                         "bit depth", "'RGB'"),
    "depth-wrong-size": (_rgb_depth("depth", 1, np.full((240, 320), 7000, np.uint16)), f"{SCENE}/depth/000001.png",
                         "size", "320x240 pixels, expected 640x480"),
    "rgb-over-pixel-limit": (lambda root: write_huge_png(scene_dir(root) / "rgb" / "000001.png"), f"{SCENE}/rgb/000001.png",
                             "size", "20000 x 20000 pixels (400 MP): more than the limit of 40 MP"),
    "gt-rotation-not-orthonormal": (_json("scene_gt.json", lambda d: d["1"][1]["cam_R_m2c"].__setitem__(0, 3.0)),
                                    f"{SCENE}/scene_gt.json", "1[1].cam_R_m2c", "not a rotation matrix"),
    "gt-rotation-reflection": (_json("scene_gt.json", lambda d: d["0"][0].update(
        cam_R_m2c=[-v for v in d["0"][0]["cam_R_m2c"]])), f"{SCENE}/scene_gt.json", "0[0].cam_R_m2c", "det = -1"),
    "image-id-not-integer": (_json("scene_gt.json", lambda d: _replace_key(d, "1", "one")), f"{SCENE}/scene_gt.json",
                             "one", "integer ids"),
    "image-id-with-underscore": (_json("scene_camera.json", lambda d: _replace_key(d, "1", "0_1")),
                                 f"{SCENE}/scene_camera.json", "0_1", "integer ids"),
    "image-id-signed": (_json("scene_gt_info.json", lambda d: _replace_key(d, "1", "+1")),
                        f"{SCENE}/scene_gt_info.json", "+1", "integer ids"),
    "gt-nan": (_json("scene_gt.json", lambda d: d["1"][0]["cam_t_m2c"].__setitem__(2, float("nan"))),
               f"{SCENE}/scene_gt.json", "1[0].cam_t_m2c", "NaN"),
    "gt-t-as-strings": (_json("scene_gt.json", lambda d: d["0"][1].update(cam_t_m2c=["110", "40", "820"])),
                        f"{SCENE}/scene_gt.json", "0[1].cam_t_m2c", "expected 3 numbers"),
    "gt-obj-id-bool": (_json("scene_gt.json", lambda d: d["0"][0].update(obj_id=True)), f"{SCENE}/scene_gt.json",
                       "0[0].obj_id", "must be an integer"),
    "cam-K-as-strings": (_json("scene_camera.json", lambda d: d["0"].update(cam_K=[str(v) for v in d["0"]["cam_K"]])),
                         f"{SCENE}/scene_camera.json", "0.cam_K", "expected 9 numbers"),
    "gt-info-fractional-box": (_json("scene_gt_info.json", lambda d: d["0"][0]["bbox_visib"].__setitem__(2, 10.5)),
                               f"{SCENE}/scene_gt_info.json", "0[0].bbox_visib", "expected 4 integers"),
    "gt-info-negative-count": (_json("scene_gt_info.json", lambda d: d["1"][2].update(px_count_visib=-4)),
                               f"{SCENE}/scene_gt_info.json", "1[2].px_count_visib", "must be >= 0"),
    "scene-camera-not-utf8": (_raw("scene_camera.json", b'{"0": {"cam_K": [\xff\xfe]}}'), f"{SCENE}/scene_camera.json",
                              "", "not a UTF-8 text file"),
    "scene-gt-info-missing": (lambda root: (scene_dir(root) / "scene_gt_info.json").unlink(),
                              f"{SCENE}/scene_gt_info.json", "", "not found"),
    "eval-mesh-truncated": (_truncate_mesh, "models_eval/obj_000001.ply", "", "cannot read mesh"),
    "eval-mesh-in-metres": (lambda root: write_models(root, scale=1e-3, obj_ids=(1,)), "models_eval/obj_000001.ply",
                            "vertex", "mm/m mix-up"),
    "eval-mesh-bad-face-index": (lambda root: _box_ply(root, 2, bad_face=True), "models_eval/obj_000002.ply", "face",
                                 "expected 0..7"),
    "eval-mesh-without-faces": (lambda root: _box_ply(root, 1, no_faces=True), "models_eval/obj_000001.ply", "vertex",
                                "point cloud"),
    "models-info-diameter-string": (_json("models/models_info.json", lambda d: d["2"].update(diameter="94.3")),
                                    "models/models_info.json", "2.diameter", "expected 1 number, got '94.3'"),
    "target-image-not-in-scene": (_json("test_targets_bop19.json", lambda d: d[3].update(im_id=9)),
                                  "test_targets_bop19.json", "[3].im_id", "image 9 not in"),
    "target-image-file-missing": (lambda root: (scene_dir(root) / "depth" / "000001.png").unlink(),
                                  f"{SCENE}/depth/000001.png", "depth", "depth image of image id 1 not found"),
    "target-inst-count-float": (_json("test_targets_bop19.json", lambda d: d[0].update(inst_count=1.0)),
                                "test_targets_bop19.json", "[0].inst_count", "non-negative integer"),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_corrupt_dataset_is_reported_and_never_scored(root: Path, capsys, name: str):
    corrupt, rel, fld, words = CORRUPTIONS[name]
    corrupt(root)
    where = f"{root / rel}" + (f" [{fld}]" if fld else "")
    rc, text = _cli(capsys, "check-dataset", str(root))
    assert rc == 1 and f"ERROR {where}: " in text, text
    assert words in next(line for line in text.splitlines() if f"ERROR {where}: " in line)
    rc, text = _eval(root, capsys)
    assert rc != 0 and f"ERROR {where}: " in text and "Traceback" not in text, text
    assert not (root.parent / "ev" / "scores.json").exists()


def test_eval_without_test_targets_is_refused(root: Path, capsys):
    (root / "test_targets_bop19.json").unlink()
    rc, text = _eval(root, capsys)
    assert rc == 1 and f"ERROR {root / 'test_targets_bop19.json'}: file not found" in text


def test_eval_of_a_missing_split_is_refused(root: Path, capsys):
    csv = _gt_csv(root)
    rc, text = _cli(capsys, "eval", "--dataset", str(root), "--results", str(csv), "--split", "val", "--no-progress")
    assert rc == 1 and f"ERROR {root / 'val'}: split folder not found" in text


@pytest.mark.parametrize("flag, value", [("--max-sym-disc-step", "0"), ("--max-sym-disc-step", "nan"),
                                         ("--visib-gt-min", "1.5"), ("--workers", "0")])
def test_eval_option_out_of_range_is_refused(root: Path, capsys, flag: str, value: str):
    csv = _gt_csv(root)
    rc, text = _cli(capsys, "eval", "--dataset", str(root), "--results", str(csv), flag, value, "--no-progress")
    assert rc == 2 and f"error: {flag} {value}" in text.lower()


def test_eval_of_a_missing_dataset_folder(tmp_path: Path, capsys):
    csv = _gt_csv(write_tiny_bop(tmp_path))
    rc, text = _cli(capsys, "eval", "--dataset", str(tmp_path / "nothere"), "--results", str(csv), "--no-progress")
    assert rc == 1 and f"ERROR {tmp_path / 'nothere'}: dataset folder not found" in text


# ----------------------------------------------------------------------------- valid input the toolkit reads


def test_cam_K_as_three_rows_is_read_as_the_toolkit_does(root: Path, capsys):
    edit_json(scene_dir(root) / "scene_camera.json",
              lambda d: d["0"].update(cam_K=np.array(d["0"]["cam_K"]).reshape(3, 3).tolist()))
    rc, text = _eval(root, capsys)
    assert rc == 0, text
    assert json.loads((root.parent / "ev" / "scores.json").read_text())["ar"] == 1.0


def test_16_bit_colour_image_is_scaled_not_stretched(tmp_path: Path):
    rgb16 = np.zeros((4, 4, 3), np.uint16)
    rgb16[0, 0] = (257 * 10, 257 * 20, 257 * 30)  # BGR on disk
    cv2.imwrite(str(tmp_path / "a.png"), rgb16)
    rgb = io.load_image(tmp_path / "a.png")
    assert rgb.dtype == np.uint8 and rgb[0, 0].tolist() == [30, 20, 10] and rgb[1, 1].tolist() == [0, 0, 0]


def test_8_bit_depth_is_refused_by_the_reader(tmp_path: Path):
    cv2.imwrite(str(tmp_path / "d.png"), np.full((4, 4), 200, np.uint8))
    with pytest.raises(BopFormatError, match=r"d\.png \[bit depth\]: uint8 pixels: expected uint16"):
        io.load_depth(tmp_path / "d.png", 0.1)
    cv2.imwrite(str(tmp_path / "d16.png"), np.full((4, 4), 7000, np.uint16))
    assert io.load_depth(tmp_path / "d16.png", 0.1)[0, 0] == pytest.approx(0.7)


def test_eval_without_depth_files_is_refused(root: Path, capsys):
    """A dataset without depth files at all: eval needs the depth (VSD) and says where it is missing."""
    shutil.rmtree(scene_dir(root) / "depth")
    rc, text = _eval(root, capsys)
    assert rc == 1 and f"ERROR {scene_dir(root) / 'depth'} [depth]: folder not found" in text


def test_missing_depth_scale_is_not_assumed_silently(root: Path, capsys):
    edit_json(scene_dir(root) / "scene_camera.json", lambda d: d["1"].pop("depth_scale"))
    rc, text = _cli(capsys, "check-dataset", str(root))
    where = f"{scene_dir(root) / 'scene_camera.json'} [depth_scale]"
    assert rc == 0 and f"WARNING {where}: missing for image ids 1 although depth images exist: 1.0 assumed" in text


def test_show_refuses_a_mask_over_the_pixel_limit_before_decoding_it(root: Path, capsys, monkeypatch):
    mask = write_huge_png(scene_dir(root) / "mask_visib" / "000000_000000.png")
    forbid_decoding(monkeypatch, mask)
    rc, text = _cli(capsys, "show", str(root), "--split", "test", "--out", str(root.parent / "show.png"))
    lines = [line for line in text.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1 and "Traceback" not in text, text
    assert lines[0].startswith(f"cosy-lite show: error: {mask} [size]: 20000 x 20000 pixels (400 MP): more than the "
                               "limit of 40 MP"), lines[0]


def test_infer_refuses_depth_of_another_size(root: Path):
    """``infer.py --icp`` reads the depth images without check-dataset: a wrong size is named there too."""
    from cosy_lite.inference.settings import InferenceConfig

    class _IcpPredictor:  # only what run_on_split touches before the poses
        config = InferenceConfig(icp=True)
        detector, coarse, refiner, obj_ids = None, None, None, [1, 2]
        reads_masks = True  # (ICP reads the masks)

    cv2.imwrite(str(scene_dir(root) / "depth" / "000000.png"), np.full((240, 320), 7000, np.uint16))
    with pytest.raises(BopFormatError, match=r"000000\.png \[size\]: 320x240 pixels, but the image .* is 640x480"):
        run_on_split(_IcpPredictor(), BopDataset(root), root.parent / "out", detections="oracle", progress=False)

"""BOP readers/writers of cosy_lite.bop.io: mm on disk <-> metres inside, and one test per
malformed input, each checking that the error names the file and the field."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from bop_fixtures import (
    BOX_MM,
    CAM_R_W2C,
    CAM_T_W2C_MM,
    DEPTH_SCALE,
    GT,
    TARGETS,
    K,
    edit_json,
    scene_dir,
    write_tiny_bop,
)

from cosy_lite.bop import io
from cosy_lite.errors import BopFormatError


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return write_tiny_bop(tmp_path)


def _raises(fn, *args) -> BopFormatError:
    with pytest.raises(BopFormatError) as info:
        fn(*args)
    return info.value


# ----------------------------------------------------------------------------- round trips


def test_models_info_mm_to_m_and_back(root: Path, tmp_path: Path):
    path = root / "models" / "models_info.json"
    infos = io.load_models_info(path)
    assert sorted(infos) == [1, 2]
    m1 = infos[1]
    assert m1.diameter == pytest.approx(np.linalg.norm(BOX_MM[1]) / 1000, abs=1e-12)
    np.testing.assert_allclose(m1.mins, [-0.05, -0.03, -0.02], atol=1e-12)
    np.testing.assert_allclose(m1.sizes, [0.1, 0.06, 0.04], atol=1e-12)
    assert not m1.is_symmetric
    m2 = infos[2]
    assert m2.symmetries_discrete.shape == (1, 4, 4)
    np.testing.assert_allclose(m2.symmetries_discrete[0][:3, 3], [0, 0, 0.010], atol=1e-12)  # 10 mm -> m
    np.testing.assert_allclose(m2.symmetries_discrete[0][:3, :3], np.diag([1, -1, -1]), atol=0)
    (axis, offset), = m2.symmetries_continuous
    np.testing.assert_allclose(axis, [0, 0, 1])
    np.testing.assert_allclose(offset, [0, 0, 0.005], atol=1e-12)

    out = tmp_path / "again" / "models_info.json"
    io.save_models_info(out, infos)
    raw_in, raw_out = json.loads(path.read_text()), json.loads(out.read_text())
    assert raw_out["2"]["symmetries_discrete"][0][11] == pytest.approx(10.0, abs=1e-9)  # back to mm
    assert raw_out["2"]["symmetries_continuous"][0]["offset"] == pytest.approx([0, 0, 5.0], abs=1e-9)
    for key in ("diameter", "min_x", "size_z"):
        assert raw_out["1"][key] == pytest.approx(raw_in["1"][key], abs=1e-9)
    again = io.load_models_info(out)
    assert again[2].diameter == pytest.approx(m2.diameter, abs=1e-15)


def test_scene_camera_round_trip(root: Path, tmp_path: Path):
    cams = io.load_scene_camera(scene_dir(root) / "scene_camera.json")
    assert sorted(cams) == [0, 1]
    c = cams[0]
    np.testing.assert_array_equal(c.K, K)
    assert c.depth_scale == DEPTH_SCALE
    np.testing.assert_allclose(c.T_CW[:3, :3], CAM_R_W2C, atol=1e-15)
    np.testing.assert_allclose(c.T_CW[:3, 3], CAM_T_W2C_MM / 1000, atol=1e-15)  # mm -> m
    out = tmp_path / "scene_camera.json"
    io.save_json(out, io.scene_camera_to_json(cams))
    assert json.loads(out.read_text())["1"]["cam_t_w2c"] == pytest.approx(CAM_T_W2C_MM.tolist(), abs=1e-9)
    again = io.load_scene_camera(out)
    np.testing.assert_allclose(again[1].T_CW, c.T_CW, atol=1e-12)
    np.testing.assert_array_equal(again[1].K, K)


def test_scene_gt_round_trip(root: Path, tmp_path: Path):
    gts = io.load_scene_gt(scene_dir(root) / "scene_gt.json", valid_obj_ids={1, 2})
    assert [len(gts[i]) for i in (0, 1)] == [2, 3]
    for im_id, instances in GT.items():
        for g, (obj_id, R, t_mm) in zip(gts[im_id], instances):
            assert g.obj_id == obj_id
            np.testing.assert_allclose(g.TCO[:3, :3], R, atol=1e-15)
            np.testing.assert_allclose(g.TCO[:3, 3], t_mm / 1000, atol=1e-15)
            np.testing.assert_array_equal(g.TCO[3], [0, 0, 0, 1])
    out = tmp_path / "scene_gt.json"
    io.save_json(out, io.scene_gt_to_json(gts))
    assert json.loads(out.read_text())["1"][2]["cam_t_m2c"] == pytest.approx(GT[1][2][2].tolist(), abs=1e-9)
    again = io.load_scene_gt(out)
    for im_id in gts:
        for a, b in zip(again[im_id], gts[im_id]):
            assert a.obj_id == b.obj_id
            np.testing.assert_allclose(a.TCO, b.TCO, atol=1e-12)


def test_scene_gt_info_round_trip(root: Path, tmp_path: Path):
    path = scene_dir(root) / "scene_gt_info.json"
    infos = io.load_scene_gt_info(path)
    raw = json.loads(path.read_text())
    first = infos[1][2]
    assert first.bbox_obj == raw["1"][2]["bbox_obj"] and first.visib_fract == 1.0
    assert first.px_count_visib == raw["1"][2]["px_count_visib"] > 0
    out = tmp_path / "scene_gt_info.json"
    io.save_json(out, io.scene_gt_info_to_json(infos))
    assert io.load_scene_gt_info(out) == infos
    assert json.loads(out.read_text()) == raw


def test_test_targets_round_trip(root: Path, tmp_path: Path):
    targets = io.load_test_targets(root / "test_targets_bop19.json", {1, 2})
    assert [(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in targets] == TARGETS
    out = tmp_path / "targets.json"
    io.save_json(out, io.targets_to_json(targets))
    assert io.load_test_targets(out) == targets


def test_depth_png_scale_0_1_to_metres(tmp_path: Path):
    depth_mm = np.array([[0.0, 400.0, 1234.5], [999.9, 2000.05, 6553.5]])
    path = tmp_path / "depth.png"
    cv2.imwrite(str(path), np.round(depth_mm / 0.1).astype(np.uint16))  # as the BOP PBR data
    d = io.load_depth(path, 0.1)
    assert d.dtype == np.float32 and d.shape == (2, 3)
    np.testing.assert_allclose(d, depth_mm / 1000, atol=0.05e-3)  # within 0.05 mm
    assert d[0, 0] == 0  # no measurement stays 0
    io.save_depth(tmp_path / "again.png", d, 0.1)
    np.testing.assert_allclose(io.load_depth(tmp_path / "again.png", 0.1), depth_mm / 1000, atol=0.05e-3)


def test_fixture_depth_matches_gt(root: Path):
    d = io.load_depth(scene_dir(root) / "depth" / "000000.png", DEPTH_SCALE)
    mask = io.load_mask(scene_dir(root) / "mask_visib" / "000000_000000.png")
    assert mask.any() and mask.dtype == bool
    np.testing.assert_allclose(d[mask], GT[0][0][2][2] / 1000, atol=0.05e-3)


def test_rgb_and_mask_round_trip(tmp_path: Path):
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0], rgb[1, 2] = 200, (1, 2, 3)  # red channel first in memory
    io.save_image(tmp_path / "im.png", rgb)
    np.testing.assert_array_equal(io.load_image(tmp_path / "im.png"), rgb)
    mask = np.eye(4, 5, dtype=bool)
    io.save_mask(tmp_path / "m.png", mask)
    np.testing.assert_array_equal(io.load_mask(tmp_path / "m.png"), mask)


def test_model_loaded_in_metres(root: Path):
    mesh = io.load_model(root / "models" / "obj_000001.ply")
    np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), np.array(BOX_MM[1]) / 1000, atol=1e-9)


# ----------------------------------------------------------------------------- malformed input


def test_missing_file(root: Path):
    path = scene_dir(root) / "scene_gt.json"
    path.unlink()
    e = _raises(io.load_scene_gt, path)
    assert e.path == str(path) and e.field == "" and "not found" in e.problem


def test_malformed_json(root: Path):
    path = scene_dir(root) / "scene_camera.json"
    path.write_text(path.read_text()[:-3])
    e = _raises(io.load_scene_camera, path)
    assert e.path == str(path) and "malformed JSON" in e.problem and "line" in e.problem


def test_non_integer_image_key(root: Path):
    path = scene_dir(root) / "scene_gt.json"
    edit_json(path, lambda d: d.update(im0=d.pop("0")))
    e = _raises(io.load_scene_gt, path)
    assert (e.path, e.field) == (str(path), "im0") and "integer" in e.problem


def test_missing_cam_K(root: Path):
    path = scene_dir(root) / "scene_camera.json"
    edit_json(path, lambda d: d["1"].pop("cam_K"))
    e = _raises(io.load_scene_camera, path)
    assert (e.path, e.field) == (str(path), "1.cam_K") and "missing" in e.problem


def test_cam_K_with_8_numbers(root: Path):
    path = scene_dir(root) / "scene_camera.json"
    edit_json(path, lambda d: d["0"]["cam_K"].pop())
    e = _raises(io.load_scene_camera, path)
    assert (e.path, e.field) == (str(path), "0.cam_K") and "expected 9 numbers, got 8" in e.problem


def test_non_orthonormal_cam_R_m2c(root: Path):
    path = scene_dir(root) / "scene_gt.json"
    edit_json(path, lambda d: d["1"][1]["cam_R_m2c"].__setitem__(0, 1.5))
    e = _raises(io.load_scene_gt, path)
    assert (e.path, e.field) == (str(path), "1[1].cam_R_m2c") and "rotation" in e.problem


def test_nan_in_cam_t_m2c(root: Path):
    path = scene_dir(root) / "scene_gt.json"
    edit_json(path, lambda d: d["0"][1]["cam_t_m2c"].__setitem__(2, float("nan")))  # JSON NaN literal
    e = _raises(io.load_scene_gt, path)
    assert (e.path, e.field) == (str(path), "0[1].cam_t_m2c") and "NaN" in e.problem


def test_cam_t_m2c_in_metres(root: Path):
    path = scene_dir(root) / "scene_gt.json"
    edit_json(path, lambda d: d["0"][0].update(cam_t_m2c=[v / 1000 for v in d["0"][0]["cam_t_m2c"]]))
    e = _raises(io.load_scene_gt, path)
    assert (e.path, e.field) == (str(path), "0[0].cam_t_m2c") and "metres" in e.problem


def test_obj_id_not_in_models_info(root: Path):
    path = scene_dir(root) / "scene_gt.json"
    edit_json(path, lambda d: d["1"][2].update(obj_id=7))
    e = _raises(io.load_scene_gt, path, {1, 2})
    assert (e.path, e.field) == (str(path), "1[2].obj_id") and "not in models_info" in e.problem


def test_models_info_diameter_in_metres(root: Path):
    path = root / "models" / "models_info.json"
    edit_json(path, lambda d: d["1"].update(diameter=d["1"]["diameter"] / 1000))
    e = _raises(io.load_models_info, path)
    assert (e.path, e.field) == (str(path), "1.diameter") and "metres" in e.problem


def test_gt_info_entry_not_a_list(root: Path):
    path = scene_dir(root) / "scene_gt_info.json"
    edit_json(path, lambda d: d.update({"1": 5}))
    e = _raises(io.load_scene_gt_info, path)
    assert (e.path, e.field) == (str(path), "1") and "list" in e.problem


def test_test_target_obj_id_not_in_models_info(root: Path):
    path = root / "test_targets_bop19.json"
    edit_json(path, lambda d: d[3].update(obj_id=9))
    e = _raises(io.load_test_targets, path, {1, 2})
    assert (e.path, e.field) == (str(path), "[3].obj_id")

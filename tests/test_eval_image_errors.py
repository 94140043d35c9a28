"""Errors of one image (``ImageErrors``): windowed VSD equals the toolkit's full-image VSD, the
toolkit's shortcuts (sphere tests) and the distance maps."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cosy_lite.bop.results import PoseEstimate
from cosy_lite.eval import pose_errors as pe
from cosy_lite.eval.depth_renderer import Window
from cosy_lite.eval.image_errors import ImageErrors
from cosy_lite.eval.object_errors import ObjectErrors
from cosy_lite.eval.scoring import VSD_TAUS

K = np.array([[600.0, 0.0, 330.0], [0.0, 610.0, 250.0], [0.0, 0.0, 1.0]])
W, H = 640, 480
EXTENTS = np.array([0.08, 0.05, 0.03])
DIAMETER = float(np.linalg.norm(EXTENTS))
DELTA = 0.015


def _pose(t, rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if any(rotvec):
        T[:3, :3] = trimesh.transformations.rotation_matrix(np.linalg.norm(rotvec), rotvec)[:3, :3]
    T[:3, 3] = t
    return T


@pytest.fixture(scope="module")
def scene():
    from cosy_lite.eval.depth_renderer import WindowDepthRenderer

    box = trimesh.creation.box(extents=EXTENTS).subdivide()
    renderer = WindowDepthRenderer({1: (box.vertices, box.faces)}, W, H)
    obj = ObjectErrors.from_model(np.asarray(box.vertices), np.eye(4)[None], DIAMETER)
    return renderer, obj


def _test_depth(renderer, T_gt: np.ndarray) -> np.ndarray:
    """The GT box on a wall at 0.9 m, a 2 cm deep occluder over its left part, a hole (no depth)."""
    full = Window(0, 0, W, H)
    depth = renderer.render(1, T_gt, K, full).astype(np.float32)
    depth[depth == 0] = 0.9
    depth[:, :300] = np.minimum(depth[:, :300], 0.45)  # in front of the box (z ~ 0.5)
    depth[255:275, 320:360] = 0.0  # no measurement: counts as visible (bop19)
    return depth


def test_windowed_vsd_equals_full_image_vsd(scene):
    renderer, obj = scene
    T_gt = _pose([0.01, 0.0, 0.5], (0.3, -0.2, 0.4))
    depth = _test_depth(renderer, T_gt)
    full = Window(0, 0, W, H)
    ests = [_pose([0.014, 0.003, 0.505], (0.32, -0.25, 0.38)), _pose([0.03, 0.01, 0.52], (0.0, 0.6, 0.2)), T_gt]
    image = ImageErrors(renderer, lambda: depth, K, DELTA)
    errs = image.target(1, obj, [PoseEstimate(0, 0, 1, 1.0, T) for T in ests], [T_gt], [0])
    dist_test = _toolkit_distance(depth)
    dist_gt = _toolkit_distance(renderer.render(1, T_gt, K, full))
    for e, T in enumerate(ests):
        expected = pe.vsd(_toolkit_distance(renderer.render(1, T, K, full)), dist_gt, dist_test, DELTA, VSD_TAUS,
                          diameter=DIAMETER)
        np.testing.assert_array_equal(errs.vsd[e, 0], expected)
    assert errs.vsd[2, 0].max() == 0.0 and errs.vsd[1, 0].min() > 0.2  # GT itself; a clearly wrong pose
    assert 0.0 < errs.vsd[0, 0, 0] < 1.0
    assert len(image._rendered) == 4  # three estimates and the GT, each rendered once


def test_toolkit_shortcuts(scene):
    renderer, obj = scene
    T_gt = _pose([0.0, 0.0, 0.5])
    far = _pose([0.0, 0.0, 0.5 + 1.01 * DIAMETER])  # spheres apart: MSSD inf; their projections overlap
    aside = _pose([0.3, 0.0, 0.5])  # projections apart: VSD 1 without rendering
    loads = []
    image = ImageErrors(renderer, lambda: loads.append(1) or np.full((H, W), 0.9, np.float32), K, DELTA)
    errs = image.target(1, obj, [PoseEstimate(0, 0, 1, 1.0, T) for T in (far, aside)], [T_gt], [0])
    assert errs.mssd[0, 0] == np.inf and errs.mssd[1, 0] == np.inf
    assert np.isfinite(errs.mspd).all()  # the toolkit has no shortcut for MSPD
    # No shortcut for ADD (it feeds the AUC only).
    assert errs.add[0, 0] == pytest.approx(1.01 * DIAMETER) and errs.add[1, 0] == pytest.approx(0.3)
    np.testing.assert_array_equal(errs.vsd[1, 0], np.ones(len(VSD_TAUS)))
    assert ("est", 1, 1) not in image._rendered and loads == [1]  # depth loaded once, for the first pair


def test_targets_without_estimates_or_gt():
    errs = ImageErrors(None, None, K, DELTA).target(1, None, [], [np.eye(4)], [0])
    assert errs.vsd.shape == (0, 1, len(VSD_TAUS)) and errs.mssd.shape == (0, 1)


def _toolkit_distance(depth: np.ndarray) -> np.ndarray:
    """The toolkit's ``depth_im_to_dist_im_fast`` of a whole [H,W] depth image (float64)."""
    xs = (np.arange(depth.shape[1]) - K[0, 2]) / K[0, 0]
    ys = (np.arange(depth.shape[0]) - K[1, 2]) / K[1, 1]
    d = depth.astype(np.float64)
    return np.sqrt((xs[None, :] * d) ** 2 + (ys[:, None] * d) ** 2 + d**2)


def _toolkit_vsd(dist_est, dist_gt, dist_test, delta, taus, diameter):
    """bop_toolkit ``pose_error.vsd`` (step cost, bop19 visibility) in numpy: the test's oracle."""
    def visible(dist_model):
        diff = dist_model.astype(np.float32) - dist_test.astype(np.float32)
        return ((diff <= delta) | (dist_test == 0)) & (dist_model > 0)

    visib_gt = visible(dist_gt)
    visib_est = visible(dist_est) | (visib_gt & (dist_est > 0))
    inter, union = visib_gt & visib_est, np.count_nonzero(visib_gt | visib_est)
    costs = np.abs(dist_gt[inter] - dist_est[inter]) / (diameter or 1.0)
    return np.array([(union - np.count_nonzero(costs < t)) / union for t in taus])


@pytest.mark.parametrize("diameter", [None, 0.08])
def test_vsd_of_depth_windows_equals_vsd_of_whole_distance_maps(diameter):
    """The compiled loop on two depth windows and the test depth: the same errors, bit for bit, as
    :func:`vsd` of whole-image distance maps (the toolkit's formula), with pixels near the
    visibility limit, holes in the test depth, and windows that overlap in part."""
    rng = np.random.default_rng(11)
    for _ in range(5):
        test = (0.6 + 0.05 * rng.random((H, W))).astype(np.float32)
        test[rng.random((H, W)) < 0.05] = 0.0  # no measurement
        gx0, gy0, ex0, ey0 = 300, 200, 310 + int(rng.integers(-20, 20)), 195 + int(rng.integers(-20, 20))
        depth_gt = test[gy0:gy0 + 60, gx0:gx0 + 80] + rng.choice([-0.01, 0.0, DELTA, 0.016, 0.03], (60, 80))
        depth_gt[rng.random(depth_gt.shape) < 0.2] = 0.0  # outside the object
        depth_gt = depth_gt.astype(np.float32)
        depth_est = (test[ey0:ey0 + 50, ex0:ex0 + 70] + rng.normal(0.0, 0.01, (50, 70))).astype(np.float32)
        depth_est[:, :5] = 0.0
        full_gt, full_est = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
        full_gt[gy0:gy0 + 60, gx0:gx0 + 80] = depth_gt
        full_est[ey0:ey0 + 50, ex0:ex0 + 70] = depth_est
        taus = VSD_TAUS if diameter else VSD_TAUS * 0.08
        dists = _toolkit_distance(full_est), _toolkit_distance(full_gt), _toolkit_distance(test)
        expected = _toolkit_vsd(*dists, DELTA, taus, diameter)
        assert 0.0 < expected.min() < expected.max() < 1.0
        np.testing.assert_array_equal(pe.vsd(*dists, DELTA, taus, diameter=diameter), expected)
        got = pe.vsd_of_depth_windows(depth_est, (ex0, ey0), depth_gt, (gx0, gy0), test, K, DELTA, taus, diameter)
        np.testing.assert_array_equal(got, expected)
    # the visibility test is float32's: delta 0.0151 m rounds up in float32, and a model 0.0151 m +
    # 2e-10 behind the test surface is visible there (in float64 it would not be)
    dist_test = np.array([[2.0**-20, 2.0**-20]])
    dist_model = np.array([[np.float32(2.0**-20) + np.float32(0.0151), 0.5]])
    assert np.float32(dist_model[0, 0]) - np.float32(2.0**-20) <= np.float32(0.0151)
    assert dist_model[0, 0] - 2.0**-20 > 0.0151
    assert pe.vsd(dist_model, dist_model, dist_test, 0.0151, [1e-9])[0] == 0.0  # the visible pixel: its cost is 0
    np.testing.assert_array_equal(_toolkit_vsd(dist_model, dist_model, dist_test, 0.0151, [1e-9], None), [0.0])

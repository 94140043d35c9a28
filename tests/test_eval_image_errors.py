"""Errors of one image (``ImageErrors``): windowed VSD equals the toolkit's full-image VSD, the
toolkit's shortcuts (sphere tests) and the distance maps."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cosy_lite.bop.results import PoseEstimate
from cosy_lite.eval import pose_errors as pe
from cosy_lite.eval.depth_renderer import Window
from cosy_lite.eval.image_errors import ImageErrors, distance_map
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
    dist_test = distance_map(depth, K, full)
    dist_gt = distance_map(renderer.render(1, T_gt, K, full), K, full)
    for e, T in enumerate(ests):
        expected = pe.vsd(distance_map(renderer.render(1, T, K, full), K, full), dist_gt, dist_test, DELTA, VSD_TAUS,
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


def test_distance_map_is_the_toolkit_formula():
    depth = np.array([[0.0, 1.0], [2.0, 0.5]], np.float32)
    win = Window(10, 20, 12, 22)
    x = (np.array([10, 11]) - K[0, 2]) / K[0, 0]
    y = (np.array([20, 21]) - K[1, 2]) / K[1, 1]
    expected = depth * np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)
    got = distance_map(depth, K, win)
    assert got.dtype == np.float64 and got[0, 0] == 0.0
    np.testing.assert_allclose(got, expected, rtol=1e-12)

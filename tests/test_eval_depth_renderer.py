"""Window depth renderer of the evaluator: pixel-centre sampling, camera-Z depth, windows equal to
full-image renders."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cosy_lite.eval.depth_renderer import EMPTY_WINDOW, Window, object_window

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
W, H = 640, 480
HALF = np.array([0.021, 0.013, 0.01])  # box half-extents (m)


def _pose(t, R=np.eye(3)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


@pytest.fixture
def renderer():
    from cosy_lite.eval.depth_renderer import WindowDepthRenderer

    box = trimesh.creation.box(extents=2 * HALF)
    return WindowDepthRenderer({3: (box.vertices, box.faces)}, W, H)


def test_front_face_depth_and_pixel_centres(renderer):
    # Front face at z = 0.5 - 0.01 = 0.49 spans u = 320 + 500 * (-0.021 .. 0.021) / 0.49 = 298.57 .. 341.43
    # and v = 240 + 500 * (-0.013 .. 0.013) / 0.49 = 226.73 .. 253.27: the pixel centres c + 0.5
    # inside are columns 299..340 (42) and rows 227..252 (26).
    depth = renderer.render(3, _pose([0.0, 0.0, 0.5]), K, Window(0, 0, W, H))
    rows, cols = np.nonzero(depth)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (227, 252, 299, 340)
    assert len(rows) == 26 * 42
    np.testing.assert_allclose(depth[depth > 0], 0.49, atol=1e-6)  # camera Z, not distance


def test_window_render_equals_full_render(renderer):
    rng = np.random.default_rng(0)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * HALF
    for _ in range(5):
        q = rng.normal(size=4)
        R = trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q))[:3, :3]
        T = _pose([rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), rng.uniform(0.3, 0.8)], R)
        full = renderer.render(3, T, K, Window(0, 0, W, H))
        win = object_window(corners, T, K, W, H)
        part = renderer.render(3, T, K, win)
        assert np.count_nonzero(full) > 100
        np.testing.assert_array_equal(part, full[win.y0:win.y1, win.x0:win.x1])
        assert np.count_nonzero(part) == np.count_nonzero(full)  # nothing rendered outside the window


def test_object_windows():
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * HALF
    # Front face u 298.57..341.43, v 226.73..253.27 (the back face projects inside): sampled columns
    # 298..341 at most, rows 226..253, plus a margin of 2 -> [296, 344) x [224, 256).
    assert object_window(corners, _pose([0.0, 0.0, 0.5]), K, W, H) == Window(296, 224, 344, 256)
    assert object_window(corners, _pose([0.0, 0.0, -0.5]), K, W, H) == EMPTY_WINDOW  # behind the camera
    assert object_window(corners, _pose([0.0, 0.0, 0.005]), K, W, H) == Window(0, 0, W, H)  # too close to bound
    assert object_window(corners, _pose([5.0, 0.0, 0.5]), K, W, H) == EMPTY_WINDOW  # outside the image
    assert Window(0, 0, 2, 2).union(Window(5, 1, 6, 9)) == Window(0, 0, 6, 9)
    assert EMPTY_WINDOW.union(Window(1, 1, 2, 2)) == Window(1, 1, 2, 2)


def test_bad_requests_raise(renderer):
    with pytest.raises(KeyError, match="obj_id 9"):
        renderer.render(9, _pose([0.0, 0.0, 0.5]), K, Window(0, 0, 4, 4))
    with pytest.raises(ValueError, match="not inside"):
        renderer.render(3, _pose([0.0, 0.0, 0.5]), K, Window(600, 0, 700, 4))


def test_the_near_plane_is_half_the_nearest_box_corner(renderer):
    # The box's front face at z = 0.004 (the plane at 2 mm) is drawn, filling the image.
    depth = renderer.render(3, _pose([0.0, 0.0, 0.014]), K, Window(0, 0, W, H))
    assert depth.max() == pytest.approx(0.004, abs=1e-9)
    assert np.count_nonzero(depth) == W * H  # the 42 x 26 mm face fills the image at 4 mm
    edge_on = _pose([0.0, 0.0, 0.0], trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])[:3, :3])
    # the box straddles the camera plane: only what lies beyond max(1 mm, 0.5 x z_min) = 1 mm is drawn
    d = renderer.render(3, edge_on, K, Window(0, 0, W, H))
    assert np.count_nonzero(d) > 1000
    assert d[d > 0].min() >= 1e-3 - 1e-12

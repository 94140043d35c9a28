"""Camera sampling: every view looks at a central object from within the configured ranges, stays
above the floor, rolls about its optical axis; YCB-V intrinsics; determinism per seed."""

from __future__ import annotations

import numpy as np
import pytest

from cosy_lite.geometry.transforms import invert_T, is_rotation, project_points, transform_points
from cosy_lite.synth.cameras import CameraConfig, central_objects, sample_camera_poses, ycbv_intrinsics

N_VIEWS = 200


@pytest.fixture(scope="module")
def pile() -> np.ndarray:
    """[12,3] object positions of a shallow pile (metres)."""
    rng = np.random.default_rng(7)
    return np.column_stack([rng.uniform(-0.2, 0.2, (12, 2)), rng.uniform(0.01, 0.12, 12)])


def _target(T_CW: np.ndarray, candidates: np.ndarray) -> tuple[int, float]:
    """The candidate nearest the optical axis and its distance to that axis (metres)."""
    p_C = transform_points(T_CW, candidates)
    off_axis = np.linalg.norm(p_C[:, :2], axis=1)
    k = int(np.argmin(off_axis))
    return k, float(off_axis[k])


def test_ycbv_intrinsics():
    K, (w, h) = ycbv_intrinsics()
    np.testing.assert_allclose(K, [[1066.778, 0, 312.9869], [0, 1067.487, 241.3109], [0, 0, 1]])
    assert (w, h) == (640, 480)


def test_central_objects():
    p = np.array([[0.3, 0.0, 0.0], [0.01, 0.0, 0.5], [-0.3, 0.05, 0.0], [0.0, -0.05, 0.0]])
    np.testing.assert_array_equal(central_objects(p, 2), [1, 3])  # centroid (0.0025, 0, .); z ignored
    np.testing.assert_array_equal(central_objects(p, 10), [1, 3, 0, 2])


def test_views_look_at_central_objects_within_ranges(pile):
    cfg = CameraConfig(lookat_jitter=0.0)
    candidates = pile[central_objects(pile, cfg.n_central)]
    poses = sample_camera_poses(pile, N_VIEWS, np.random.default_rng(0), cfg)
    assert len(poses) == N_VIEWS
    seen = set()
    for T_CW in poses:
        assert is_rotation(T_CW[:3, :3], atol=1e-9)
        k, off_axis = _target(T_CW, candidates)
        assert off_axis < 1e-9  # the optical axis passes exactly through a central object
        seen.add(k)
        eye = invert_T(T_CW)[:3, 3]
        d = np.linalg.norm(eye - candidates[k])
        assert cfg.distance[0] - 1e-9 <= d <= cfg.distance[1] + 1e-9
        elevation = np.arcsin((eye[2] - candidates[k][2]) / d)
        assert cfg.elevation[0] - 1e-9 <= elevation <= cfg.elevation[1] + 1e-9
        assert eye[2] > 0.15  # well above the floor
        assert transform_points(T_CW, candidates[k][None])[0, 2] == pytest.approx(d)  # in front
    assert seen == {0, 1, 2}


def test_target_projects_in_central_part_of_image(pile):
    """With the default look-at jitter, the looked-at object stays in the central 60% of the image."""
    cfg = CameraConfig()
    K, (w, h) = ycbv_intrinsics()
    candidates = pile[central_objects(pile, cfg.n_central)]
    for T_CW in sample_camera_poses(pile, N_VIEWS, np.random.default_rng(1), cfg):
        k, off_axis = _target(T_CW, candidates)
        assert off_axis <= cfg.lookat_jitter * np.sqrt(3) + 1e-9
        u, v = project_points(transform_points(T_CW, candidates[k][None]), K)[0]
        assert 0.2 * w <= u <= 0.8 * w and 0.2 * h <= v <= 0.8 * h


def test_inplane_rotation_azimuth_and_elevation_vary(pile):
    poses = sample_camera_poses(pile, N_VIEWS, np.random.default_rng(2), CameraConfig())
    # Roll: direction of the world up axis in the image (always -v without in-plane rotation).
    up_C = np.stack([T[:3, :3] @ np.array([0.0, 0.0, 1.0]) for T in poses])
    roll = np.arctan2(up_C[:, 1], up_C[:, 0])
    assert np.histogram(roll, bins=8, range=(-np.pi, np.pi))[0].min() >= 10  # about uniform over the circle
    eyes = np.stack([invert_T(T)[:3, 3] for T in poses])
    azimuth = np.arctan2(eyes[:, 1], eyes[:, 0])
    assert np.histogram(azimuth, bins=4, range=(-np.pi, np.pi))[0].min() >= 25
    assert eyes[:, 2].max() - eyes[:, 2].min() > 0.5

    upright = sample_camera_poses(pile, 20, np.random.default_rng(2), CameraConfig(inplane=(0.0, 0.0)))
    up_C = np.stack([T[:3, :3] @ np.array([0.0, 0.0, 1.0]) for T in upright])
    np.testing.assert_allclose(np.arctan2(up_C[:, 1], up_C[:, 0]), -np.pi / 2, atol=1e-9)


def test_deterministic_per_seed(pile):
    a = sample_camera_poses(pile, 10, np.random.default_rng(3), CameraConfig())
    b = sample_camera_poses(pile, 10, np.random.default_rng(3), CameraConfig())
    c = sample_camera_poses(pile, 10, np.random.default_rng(4), CameraConfig())
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not any(np.allclose(x, y) for x, y in zip(a, c))


def test_bad_inputs(pile):
    with pytest.raises(ValueError, match="object_positions_W"):
        sample_camera_poses(pile[:, :2], 1, np.random.default_rng(0), CameraConfig())
    with pytest.raises(ValueError, match="above the floor"):
        sample_camera_poses(pile, 1, np.random.default_rng(0), CameraConfig(elevation=(-0.2, 0.5)))

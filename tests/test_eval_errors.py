"""Pose errors against hand-computed values: MSSD/MSPD/ADD/ADI of known offsets and symmetries,
VSD on synthetic distance maps and on rendered symmetric poses."""

from __future__ import annotations

import numpy as np
import pytest

from cosy_lite.bop.io import ModelInfo
from cosy_lite.eval import pose_errors as pe
from cosy_lite.geometry.symmetries import symmetry_transforms

HALF = np.array([0.05, 0.03, 0.02])  # box half-extents [m]
BOX = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * HALF  # [8,3]
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])


def _pose(R: np.ndarray = np.eye(3), t=(0.0, 0.0, 0.5)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _flip(axis: int) -> np.ndarray:
    """180 deg about a model axis, as a [4,4] symmetry."""
    d = -np.ones(3)
    d[axis] = 1.0
    return _pose(np.diag(d), (0.0, 0.0, 0.0))


def _box_info() -> ModelInfo:
    return ModelInfo(1, float(2 * np.linalg.norm(HALF)), -HALF, 2 * HALF, np.stack([_flip(0), _flip(1), _flip(2)]))


ID = np.eye(4)[None]


def test_translation_of_10mm_along_x():
    gt = _pose(t=(0.0, 0.0, 0.5))
    est = _pose(t=(0.01, 0.0, 0.5))
    assert pe.mssd(est, gt, BOX, ID) == pytest.approx(0.01, abs=1e-12)
    assert pe.add(est, gt, BOX) == pytest.approx(0.01, abs=1e-12)
    # Fronto-parallel planar object at z = 0.5: every point moves fx * 0.01 / z = 12 px.
    square = np.array([[x, y, 0.0] for x in (-0.04, 0.0, 0.04) for y in (-0.04, 0.04)])
    assert pe.mspd(est, gt, K, square, ID) == pytest.approx(600.0 * 0.01 / 0.5, abs=1e-9)
    # For the box the front face (z = 0.48) moves most: 600 * 0.01 / 0.48 px.
    assert pe.mspd(est, gt, K, BOX, ID) == pytest.approx(600.0 * 0.01 / 0.48, abs=1e-9)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_pose_rotated_by_a_declared_symmetry_has_zero_mssd_mspd(axis: int):
    syms = symmetry_transforms(_box_info())
    assert len(syms) == 4 and np.allclose(syms[0], np.eye(4))
    gt = _pose(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), (0.02, -0.01, 0.6))
    est = gt @ _flip(axis)
    assert pe.mssd(est, gt, BOX, syms) == pytest.approx(0.0, abs=1e-12)
    assert pe.mspd(est, gt, K, BOX, syms) == pytest.approx(0.0, abs=1e-9)
    assert pe.adi(est, gt, BOX) == pytest.approx(0.0, abs=1e-12)
    # Without symmetries the flip about z moves (x, y, z) to (-x, -y, z): 2 |(x, y)| at every corner.
    if axis == 2:
        expected = 2 * np.linalg.norm(HALF[:2])
        assert pe.mssd(est, gt, BOX, ID) == pytest.approx(expected, abs=1e-12)
        assert pe.add(est, gt, BOX) == pytest.approx(expected, abs=1e-12)


def test_mssd_takes_the_best_symmetry_and_chunks(monkeypatch):
    monkeypatch.setattr(pe, "SYM_CHUNK_POINTS", 8)  # one symmetry per chunk
    syms = symmetry_transforms(_box_info())
    gt = _pose()
    est = gt @ _flip(1) @ _pose(t=(0.003, 0.0, 0.0))  # flipped, then 3 mm along model x
    assert pe.mssd(est, gt, BOX, syms) == pytest.approx(0.003, abs=1e-12)


def test_batched_mssd_mspd_equal_single_calls():
    syms = symmetry_transforms(_box_info())
    gt = _pose(t=(0.01, 0.0, 0.6))
    ests = np.stack([gt @ _flip(1), gt @ _pose(t=(0.0, 0.004, 0.0)), _pose(t=(0.03, 0.02, 0.7))])
    m3, m2 = pe.mssd_mspd(ests, gt, K, BOX, syms)
    np.testing.assert_allclose(m3, [pe.mssd(e, gt, BOX, syms) for e in ests], atol=1e-12)
    np.testing.assert_allclose(m2, [pe.mspd(e, gt, K, BOX, syms) for e in ests], atol=1e-9)
    assert m3[1] == pytest.approx(0.004, abs=1e-12)


def test_continuous_symmetry_discretisation():
    cyl = np.array([[0.03 * np.cos(a), 0.03 * np.sin(a), z] for a in np.linspace(0, 2 * np.pi, 72, endpoint=False)
                    for z in (-0.05, 0.05)])
    info = ModelInfo(1, 0.1, -np.array([0.03, 0.03, 0.05]), np.array([0.06, 0.06, 0.1]),
                     symmetries_continuous=[(np.array([0.0, 0.0, 1.0]), np.zeros(3))])
    syms = symmetry_transforms(info)
    gt = _pose()
    est = gt @ syms[100]  # exactly a discretised rotation about z
    assert pe.mssd(est, gt, cyl, syms) == pytest.approx(0.0, abs=1e-12)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="pts"):
        pe.mssd(np.eye(4), np.eye(4), np.zeros((3, 2)), ID)
    with pytest.raises(ValueError, match="syms"):
        pe.mssd(np.eye(4), np.eye(4), BOX, np.zeros((0, 4, 4)))
    with pytest.raises(ValueError, match="TCO_est"):
        pe.add(np.eye(3), np.eye(4), BOX)


def test_sphere_projections_overlap():
    assert pe.sphere_projections_overlap(0.05, np.array([0.0, 0, 1]), np.array([0.09, 0, 1]))
    assert not pe.sphere_projections_overlap(0.05, np.array([0.0, 0, 1]), np.array([0.11, 0, 1]))


# ----------------------------------------------------------------------------- VSD, synthetic maps

TAUS = np.array([0.02, 0.05])
DELTA = 0.015


def _maps(shift: int = 0, est_depth: float = 0.8, gt_depth: float = 0.8):
    test = np.full((20, 30), 1.0, np.float32)
    gt = np.zeros_like(test)
    gt[5:15, 5:15] = gt_depth
    est = np.zeros_like(test)
    est[5:15, 5 + shift:15 + shift] = est_depth
    return est, gt, test


def test_vsd_identical_is_zero_and_shift_counts_pixels():
    est, gt, test = _maps()
    np.testing.assert_allclose(pe.vsd(est, gt, test, DELTA, TAUS), [0.0, 0.0])
    # 5-column shift of a 10x10 square: union 150 px, 50 matching px -> 100 / 150.
    est, gt, test = _maps(shift=5)
    np.testing.assert_allclose(pe.vsd(est, gt, test, DELTA, TAUS), [2 / 3, 2 / 3])


def test_vsd_per_tau_cost():
    # 3 cm deeper estimate: still visible (test surface 20 cm behind); cost 0.03 fails tau 2 cm, passes 5 cm.
    est, gt, test = _maps(est_depth=0.83)
    np.testing.assert_allclose(pe.vsd(est, gt, test, DELTA, TAUS), [1.0, 0.0])


def test_vsd_occluded_and_empty():
    # Both poses behind the test surface by more than delta: nothing visible -> error 1.
    est, gt, test = _maps(est_depth=1.2, gt_depth=1.2)
    np.testing.assert_allclose(pe.vsd(est, gt, test, DELTA, TAUS), [1.0, 1.0])
    # No test measurement (0) counts as visible.
    test[:] = 0
    np.testing.assert_allclose(pe.vsd(est, gt, test, DELTA, TAUS), [0.0, 0.0])


# ----------------------------------------------------------------------------- VSD, rendered


def _render(poses: np.ndarray) -> list[np.ndarray]:
    """The box's depth at each pose, full 640x480 image (the evaluator's rasteriser)."""
    import trimesh

    from cosy_lite.render.depth_raster import mesh_arrays, rasterize_depth

    box = trimesh.creation.box(extents=2 * HALF)
    mesh = mesh_arrays(box.vertices, box.faces)
    return [rasterize_depth(*mesh, T, K, (0, 0, 640, 480)) for T in poses]


def test_vsd_of_a_symmetric_pose_is_zero_when_rendered():
    from cosy_lite.geometry.depth import depth_to_distance

    gt = _pose(np.array([[1.0, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]]), (0.01, 0.02, 0.5))
    poses = np.stack([gt, gt @ _flip(0), gt @ _flip(1), gt @ _flip(2), gt @ _pose(t=(0.01, 0.0, 0.0))])
    depth = _render(poses)
    dist = [depth_to_distance(d, K) for d in depth]
    test = np.zeros((480, 640), np.float32)  # no measurement: everything visible
    taus = np.arange(0.05, 0.51, 0.05) * 2 * np.linalg.norm(HALF)
    for i in (1, 2, 3):
        e = pe.vsd(dist[i], dist[0], test, DELTA, taus)
        assert e.max() < 2e-3, (i, e)  # a few silhouette pixels may differ by rasterisation
    assert pe.vsd(dist[4], dist[0], test, DELTA, taus).min() > 0.05  # a 1 cm shift is seen


def test_mssd_mspd_equal_the_toolkit_loops_with_continuous_symmetry():
    rng = np.random.default_rng(1)
    pts = rng.normal(0, 0.03, (50, 3))
    info = ModelInfo(1, 0.15, pts.min(0), np.ptp(pts, 0), _flip(0)[None],
                     [(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.005]))])
    syms = symmetry_transforms(info, 0.05)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    gt = _pose(R * np.linalg.det(R), (0.02, -0.03, 0.7))  # proper rotation
    est = gt @ syms[7] @ _pose(t=(0.002, -0.001, 0.003))
    loop3 = min(np.linalg.norm(pe.transform_points(est, pts) - pe.transform_points(gt @ S, pts), axis=1).max()
                for S in syms)
    loop2 = min(np.linalg.norm(pe.project_points(pe.transform_points(est, pts), K)
                               - pe.project_points(pe.transform_points(gt @ S, pts), K), axis=1).max() for S in syms)
    m3, m2 = pe.mssd_mspd(est[None], gt, K, pts, syms)
    assert m3[0] == pytest.approx(loop3, abs=1e-12) and m2[0] == pytest.approx(loop2, abs=1e-9)
    assert m3[0] <= np.linalg.norm([0.002, 0.001, 0.003]) + 1e-12


def test_vsd_costs_normalised_by_diameter():
    # Cost 0.03 m (float32 maps: 0.02999997); diameter 0.2 -> 0.15 x diameter: a miss for tau 0.10
    # and 0.14 (cost >= tau), a match for 0.16. Same as tau x diameter in metres.
    est, gt, test = _maps(est_depth=0.83)
    np.testing.assert_allclose(pe.vsd(est, gt, test, DELTA, [0.10, 0.14, 0.16], diameter=0.2), [1.0, 1.0, 0.0])
    np.testing.assert_allclose(pe.vsd(est, gt, test, DELTA, [0.02, 0.028, 0.032]), [1.0, 1.0, 0.0])


def test_sphere_projections_at_zero_depth_do_not_overlap():
    # The toolkit returns False when a centre has z = 0 (no projection), before dividing.
    assert not pe.sphere_projections_overlap(0.05, np.array([0.0, 0, 0]), np.array([0.0, 0, 1]))
    assert pe.sphere_projections_overlap(0.05, np.array([0.0, 0, 2]), np.array([0.0, 0, 1]))

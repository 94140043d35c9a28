"""Symmetry discovery (BOP 2020 criterion + colour test) and the BOP toolkit's discretisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist

from cosy_lite.bop.io import ModelInfo
from cosy_lite.geometry.symmetries import find_symmetries, symmetry_tolerance, symmetry_transforms
from cosy_lite.geometry.transforms import is_rotation, make_T, rotation_about_axis


def _diameter(v: np.ndarray) -> float:
    return float(pdist(v).max())


def _hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    return max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max())


def _info(v: np.ndarray, discrete: np.ndarray, continuous: list) -> ModelInfo:
    return ModelInfo(1, _diameter(v), v.min(axis=0), np.ptp(v, axis=0), discrete, continuous)


@pytest.fixture(scope="module")
def cylinder() -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=0.04, height=0.1)  # axis z, centred, 66 vertices


def test_tolerance_is_the_papers():
    assert symmetry_tolerance(0.1) == 0.015  # truncated at 15 mm
    assert symmetry_tolerance(0.3) == pytest.approx(0.03)  # 0.1 * diameter


def test_cylinder_continuous_about_z_plus_one_flip(cylinder):
    v = cylinder.vertices
    discrete, continuous = find_symmetries(v, _diameter(v))
    assert len(continuous) == 1
    axis, offset = continuous[0]
    assert abs(abs(axis[2]) - 1.0) < 1e-6 and np.allclose(offset, 0.0, atol=1e-9)
    assert len(discrete) == 1  # the upside-down flip; the continuous rotations generate the others
    R = discrete[0][:3, :3]
    assert is_rotation(R) and np.trace(R) == pytest.approx(-1.0)  # a 180 deg rotation
    flip_axis = np.linalg.eigh(R + R.T)[1][:, -1]  # eigenvector of eigenvalue 1
    assert abs(flip_axis[2]) < 1e-6  # horizontal
    assert np.allclose(discrete[0][:3, 3], 0.0, atol=1e-9)


def test_box_has_the_three_flips():
    v = trimesh.creation.box([0.1, 0.06, 0.03]).vertices
    discrete, continuous = find_symmetries(v, _diameter(v))
    assert continuous == []
    got = sorted(tuple(np.round(np.diag(S[:3, :3])).astype(int)) for S in discrete)
    assert got == [(-1, -1, 1), (-1, 1, -1), (1, -1, -1)]
    for S in discrete:
        assert np.allclose(S[:3, :3], np.diag(np.diag(S[:3, :3])), atol=1e-9)
        assert np.allclose(S[:3, 3], 0.0, atol=1e-9)


def test_asymmetric_shape_has_none():
    box = trimesh.creation.box([0.1, 0.06, 0.03])
    bump = trimesh.creation.box([0.03, 0.03, 0.03])  # 30 mm > eps = 15 mm, at one end, on top
    bump.apply_translation([0.035, 0.0, 0.03])
    v = trimesh.util.concatenate([box, bump]).vertices
    discrete, continuous = find_symmetries(v, _diameter(v))
    assert len(discrete) == 0 and continuous == []


def test_colour_resolves_the_continuous_symmetry(cylinder):
    v = cylinder.vertices
    colors = np.where(v[:, :1] > 1e-6, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])  # red half x > 0, blue half
    _, continuous_geo = find_symmetries(v, _diameter(v))
    discrete, continuous = find_symmetries(v, _diameter(v), colors=colors)
    assert len(continuous_geo) == 1 and continuous == []
    for S in discrete:  # what survives keeps the red half where it is: the flip about x only
        assert S[0, 0] == pytest.approx(1.0)


def test_explicit_axes_and_centre():
    v = trimesh.creation.box([0.1, 0.06, 0.03]).vertices + [0.2, 0.0, 0.0]  # off-origin box
    discrete, _ = find_symmetries(v, _diameter(v), axes=[np.array([0.0, 0.0, 2.0])])
    assert len(discrete) == 1  # only 180 deg about z is a candidate now
    S = discrete[0]
    assert np.allclose(S[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-9)
    assert np.allclose(S[:3, 3], [0.4, 0.0, 0.0], atol=1e-9)  # t = c - R c, c = (0.2, 0, 0)
    assert _hausdorff(v @ S[:3, :3].T + S[:3, 3], v) < 1e-9


def test_a_dense_mesh_is_tested_on_a_subsample_and_keeps_its_symmetries(monkeypatch):
    """Above ``max_points`` vertices only an even stride of them is transformed (the cost is bounded by
    the sample, not the mesh; no wall-clock bound, which a busy machine would break), and the sample
    still finds the cylinder's continuous axis and its flip."""
    import scipy.spatial

    mesh = trimesh.creation.cylinder(radius=0.04, height=0.1, sections=256).subdivide().subdivide()
    assert len(mesh.vertices) > 5000
    queried: list[int] = []
    real_tree = scipy.spatial.cKDTree  # (symmetries imports it where it builds the tree)

    class CountingTree(real_tree):
        def query(self, x, *args, **kwargs):
            queried.append(len(x))
            return super().query(x, *args, **kwargs)

    monkeypatch.setattr(scipy.spatial, "cKDTree", CountingTree)
    discrete, continuous = find_symmetries(mesh.vertices, _diameter(mesh.vertices[::4]), max_points=500)
    assert queried and max(queried) <= 500
    assert len(continuous) == 1 and abs(abs(float(continuous[0][0][2])) - 1.0) < 1e-6
    assert len(discrete) == 1 and is_rotation(discrete[0][:3, :3])


# ----------------------------------------------------------------------------- BOP discretisation


def test_continuous_count_and_rigidity(cylinder):
    v = cylinder.vertices
    discrete, continuous = find_symmetries(v, _diameter(v))
    info = _info(v, discrete, continuous)
    T = symmetry_transforms(info, max_sym_disc_step=0.01, include_zero_angle=False)
    n = math.ceil(math.pi / 0.01)
    assert n == 315
    assert T.shape == ((n - 1) * (1 + len(discrete)), 4, 4) == (628, 4, 4)
    for S in T:
        assert is_rotation(S[:3, :3], atol=1e-9)
        assert np.array_equal(S[3], [0.0, 0.0, 0.0, 1.0])
    eps = symmetry_tolerance(info.diameter)
    tree = cKDTree(v)
    moved = np.einsum("nij,vj->nvi", T[:, :3, :3], v) + T[:, None, :3, 3]
    assert tree.query(moved.reshape(-1, 3))[0].max() < eps
    # The older toolkit's quirk: i in 1..n-1, so the identity is not in the set; the current
    # toolkit (our default) starts at i = 0.
    assert not any(np.allclose(S, np.eye(4)) for S in T)
    T0 = symmetry_transforms(info, 0.01)
    assert len(T0) == n * 2 and np.allclose(T0[0], np.eye(4))


def test_toolkit_order_and_offset():
    """Order d-major then c (R = Rc Rd, t = Rc td + tc); t = offset - R offset for the axis through offset."""
    flip = make_T(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.0])
    offset = np.array([0.01, 0.02, 0.0])
    info = ModelInfo(1, 0.1, np.zeros(3), np.ones(3) * 0.1, flip[None], [(np.array([0.0, 0.0, 1.0]), offset)])
    T = symmetry_transforms(info, max_sym_disc_step=math.pi / 4, include_zero_angle=False)  # n = 4: 90, 180, 270 deg
    assert T.shape == (6, 4, 4)
    for i, k in enumerate((1, 2, 3)):
        R = rotation_about_axis(np.array([0.0, 0.0, 1.0]), k * math.pi / 2)
        Tc = make_T(R, offset - R @ offset)
        assert np.allclose(T[i], Tc, atol=1e-12)  # identity (d = 0) first
        assert np.allclose(T[3 + i], Tc @ flip, atol=1e-12)
    p = offset + np.array([0.0, 0.0, 0.05])  # points on the axis stay put
    assert np.allclose(T[:3, :3, :3] @ p + T[:3, :3, 3], p, atol=1e-12)


def test_pure_discrete_identity_first():
    v = trimesh.creation.box([0.1, 0.06, 0.03]).vertices
    discrete, continuous = find_symmetries(v, _diameter(v))
    T = symmetry_transforms(_info(v, discrete, continuous))
    assert T.shape == (4, 4, 4)
    assert np.array_equal(T[0], np.eye(4))
    assert np.allclose(T[1:], discrete)
    assert len(symmetry_transforms(_info(v, np.zeros((0, 4, 4)), []))) == 1

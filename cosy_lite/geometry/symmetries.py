"""Global object symmetries (metres): discovery, and the BOP discretisation used by MSSD/MSPD.

Three functions:

* :func:`symmetry_transforms` turns an object's symmetries (:class:`SymmetryInfo`, e.g. a
  :class:`~cosy_lite.bop.io.ModelInfo`) into the finite set of
  transformations the BOP toolkit (``misc.get_symmetry_transformations``) evaluates MSSD/MSPD with.
* :func:`find_symmetries` identifies the symmetries of a model as in the BOP Challenge 2020 paper
  (Sec. "Identifying Global Object Symmetries"): a transformation ``S`` is a candidate if the
  Hausdorff distance between the vertices ``V`` and ``S V`` is below
  ``eps = max(15 mm, 0.1 * diameter)``; the second step, dropping symmetries the texture resolves
  (done by hand by the organisers), is automated with a colour test.
* :func:`rotation_errors_deg`: the angle from a rotation to the closest pose of a symmetry set.

A symmetry ``S`` maps model coordinates to model coordinates: ``x' = S[:3,:3] @ x + S[:3,3]``.
"""

from __future__ import annotations

import math
from typing import Protocol, Sequence

import numpy as np

EPS_MIN = 0.015  # m, the paper's truncation of the Hausdorff tolerance
EPS_DIAMETER_FRACTION = 0.1  # eps = max(EPS_MIN, 0.1 * diameter)
DISCRETE_ORDERS = (2, 3, 4, 6)  # candidate rotations 2*pi*k/n about each axis
CONTINUOUS_STEP_DEG = 10.0  # an axis is continuous if every rotation by a multiple of this passes
MAX_POINTS = 5000  # vertices kept (deterministically) as the transformed sample

# Mean RGB distance (colours in [0, 1], Euclidean, max sqrt(3)) between each transformed sample
# vertex and its nearest model vertex at or above which the texture resolves a geometric symmetry.
# Calibrated on the YCB-V library of cosy_lite/synth/objects.py (textures sampled box-filtered to
# 64x64): symmetries the procedural colours keep score 0.01-0.04 (bowl, master chef and tuna cans,
# wood block flips, foam brick); those they break score >= 0.11 (banana flip 0.115, wood block
# 45 deg 0.21, pudding box >= 0.17); the printed labels of the six textured objects score >= 0.15
# on every geometric symmetry. Caveat: a 3 deg rotation of a printed label already scores
# 0.03-0.11 (texture detail), so a true symmetry of a finely printed texture may be rejected.
COLOUR_THRESHOLD = 0.08


class SymmetryInfo(Protocol):
    """The symmetries of an object as ``models_info.json`` lists them, in metres: what
    :func:`symmetry_transforms` reads (a :class:`~cosy_lite.bop.io.ModelInfo` is one; geometry
    does not depend on the BOP readers)."""

    @property
    def symmetries_discrete(self) -> np.ndarray:  # [S,4,4], t in m
        ...

    @property
    def symmetries_continuous(self) -> Sequence[tuple[np.ndarray, np.ndarray]]:  # (axis [3], offset [3] m)
        ...


def symmetry_tolerance(diameter: float) -> float:
    """The paper's Hausdorff tolerance eps = max(15 mm, 0.1 * diameter), in metres."""
    return max(EPS_MIN, EPS_DIAMETER_FRACTION * float(diameter))


def rotations_about_axis(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rodrigues, vectorised: rotations [A,3,3] by ``angles`` [A] (radians) about ``axis`` [3] (normalised here)."""
    a = np.asarray(axis, dtype=np.float64).reshape(3)
    a = a / np.linalg.norm(a)
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    Kx = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3) + s * Kx + (1.0 - c) * (Kx @ Kx)


def _rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[...,3,3] rotations + [...,3] translations -> [...,4,4]."""
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


# ----------------------------------------------------------------------------- BOP discretisation


def symmetry_transforms(info: SymmetryInfo, max_sym_disc_step: float = 0.01, include_zero_angle: bool = True) -> np.ndarray:
    """The symmetry set [N,4,4] (t in metres) as the BOP toolkit's ``get_symmetry_transformations``.

    Discrete set D = identity (first) + ``info.symmetries_discrete``. Each continuous symmetry
    (axis, offset) is discretised with ``n = ceil(pi / max_sym_disc_step)`` steps of ``2 pi / n``:
    rotations by ``i * step`` about the axis through ``offset`` (t = offset - R offset), the
    rotations of all continuous symmetries pooled into one list C (they are NOT composed with each
    other). The result is every ``c @ d`` (R = Rc Rd, t = Rc td + tc), ordered d-major then c
    (the toolkit's loops); with no continuous symmetry it is D itself.

    Default (``include_zero_angle=True``): ``i`` in ``0..n-1``, as the current bop_toolkit
    (after its fix "missing identity in get_symmetry_transformations", mid 2023).
    ``include_zero_angle=False`` reproduces the older toolkit (BOP 2019-2022 evaluations,
    CosyPose): ``i`` in ``1..n-1``, so for an object with only a continuous symmetry the identity
    is NOT in the set (n - 1 = 314 transforms for step 0.01).
    """
    disc = np.concatenate([np.eye(4)[None], np.asarray(info.symmetries_discrete, dtype=np.float64).reshape(-1, 4, 4)])
    if not info.symmetries_continuous:
        return disc
    n = int(np.ceil(np.pi / max_sym_disc_step))
    angles = np.arange(0 if include_zero_angle else 1, n) * (2.0 * np.pi / n)
    cont = []
    for axis, offset in info.symmetries_continuous:
        R = rotations_about_axis(axis, angles)
        offset = np.asarray(offset, dtype=np.float64).reshape(3)
        cont.append(_rigid(R, offset - R @ offset))
    C = np.concatenate(cont)
    return (C[None, :] @ disc[:, None]).reshape(-1, 4, 4)


# ----------------------------------------------------------------------------- discovery


class _Checker:
    """Hausdorff (and colour) test of candidate transformations against one vertex set.

    The transformed sample (``max_points`` vertices, an even stride through the vertex list) is
    matched to the nearest of ALL vertices (cKDTree). A cheap pre-test on ~1/8 of the sample
    rejects most candidates; results are cached, so axes shared by several frames cost nothing.
    """

    def __init__(self, vertices: np.ndarray, eps: float, colors: np.ndarray | None, colour_threshold: float, max_points: int):
        from scipy.spatial import cKDTree  # (imported here: the evaluator's symmetry tables need no scipy)

        self.tree = cKDTree(vertices)
        n = len(vertices)
        idx = np.arange(n) if n <= max_points else np.round(np.linspace(0, n - 1, max_points)).astype(np.int64)
        self.points = vertices[idx]
        self.colors = colors
        self.point_colors = None if colors is None else colors[idx]
        self.eps = eps
        self.colour_threshold = colour_threshold
        self._cache: dict[tuple, bool] = {}

    def _passes(self, T: np.ndarray, sl: slice) -> bool:
        moved = self.points[sl] @ T[:3, :3].T + T[:3, 3]
        dist, nn = self.tree.query(moved, distance_upper_bound=self.eps)
        if not np.all(np.isfinite(dist)):
            return False
        if self.colors is None:
            return True
        assert self.point_colors is not None  # set with colors in __init__
        return float(np.linalg.norm(self.point_colors[sl] - self.colors[nn], axis=1).mean()) < self.colour_threshold

    def directed(self, T: np.ndarray) -> bool:
        """True if every transformed sample vertex lies within eps of a vertex (and colours match)."""
        key = tuple(np.round(T[:3, :4], 7).ravel())
        if key not in self._cache:
            self._cache[key] = self._passes(T, slice(None, None, 8)) and self._passes(T, slice(None))
        return self._cache[key]

    def symmetric(self, T: np.ndarray) -> bool:
        """Symmetric Hausdorff test: h(V, S V) < eps both ways (S^-1 V checks the other direction)."""
        Ti = np.eye(4)
        Ti[:3, :3] = T[:3, :3].T
        Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
        return self.directed(T) and self.directed(Ti)


def candidate_frames(vertices: np.ndarray) -> list[np.ndarray]:
    """Orthonormal frames [3,3] (rows = axes) whose axes are tried as symmetry axes, in order:
    the model frame, the minimum-volume oriented bounding box (boxes rotated in the model frame),
    the principal axes of the vertex covariance; a frame within 3 deg of an earlier one is dropped."""
    import trimesh

    v = np.asarray(vertices, dtype=np.float64)
    T_obb, _ = trimesh.bounds.oriented_bounds(v)
    _, vecs = np.linalg.eigh(np.cov((v - v.mean(axis=0)).T))
    frames: list[np.ndarray] = []
    for F in (np.eye(3), T_obb[:3, :3], vecs.T[::-1]):
        F = F * np.sign(F[np.arange(3), np.argmax(np.abs(F), axis=1)])[:, None]  # deterministic signs
        near = lambda G, F=F: all(np.abs(G @ a).max() > math.cos(math.radians(3.0)) for a in F)  # noqa: E731
        if not any(near(G) for G in frames):
            frames.append(F)
    return frames


def _discrete_angles() -> list[float]:
    """Distinct angles 2 pi k / n (0 < k < n, n in DISCRETE_ORDERS), ascending."""
    fractions = {(k // math.gcd(k, n), n // math.gcd(k, n)) for n in DISCRETE_ORDERS for k in range(1, n)}
    return sorted(2.0 * math.pi * k / n for k, n in fractions)


def _about(axis: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    R = rotations_about_axis(axis, np.array([angle]))[0]
    return _rigid(R, centre - R @ centre)


def _same(A: np.ndarray, B: np.ndarray, atol: float = 1e-3) -> bool:
    return bool(np.abs(A[:3, :3] - B[:3, :3]).max() < atol and np.abs(A[:3, 3] - B[:3, 3]).max() < atol * 0.1)


def _close_group(gens: list[np.ndarray], checker: _Checker, max_size: int = 48) -> list[np.ndarray]:
    """Close the discrete set under composition (e.g. 90 deg about z + 180 deg about x gives the
    diagonal flips): products ``g @ A`` of a generator and a found element, kept if they pass the
    test (approximate symmetries need not form a group). Identity excluded, at most ``max_size``."""
    elems = [np.eye(4)] + list(gens)
    frontier = list(gens)
    while frontier and len(elems) < max_size:
        new: list[np.ndarray] = []
        for A in frontier:
            for g in gens:
                C = g @ A
                if not any(_same(C, E) for E in elems + new) and checker.symmetric(C):
                    new.append(C)
        elems += new
        frontier = new
    return elems[1:max_size]


def find_symmetries(
    vertices: np.ndarray,
    diameter: float,
    colors: np.ndarray | None = None,
    axes: list[np.ndarray] | None = None,
    centre: np.ndarray | None = None,
    colour_threshold: float = COLOUR_THRESHOLD,
    max_points: int = MAX_POINTS,
) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Global rotational symmetries of a model, by the BOP 2020 criterion (automated).

    Args:
        vertices: [N,3] model vertices (m). diameter: the model diameter (m).
        colors: optional [N,3] per-vertex RGB in [0, 1]; if given, a geometric symmetry is kept
            only if the mean colour distance after the transformation is < ``colour_threshold``.
        axes: candidate axes [3] searched together; default: each frame of :func:`candidate_frames`
            (model axes, oriented bounding box, principal axes) searched on its own, and the frame
            with the most symmetries (continuous first, then discrete) wins.
        centre: [3] point the axes pass through (m); default the centre of the bounding box.
        max_points: vertices transformed per test (an even stride through ``vertices``); they are
            matched against all vertices. ~0.1-0.5 s for the 8k-vertex YCB meshes.
    Returns:
        discrete [S,4,4] (rotation R about an axis through the centre c, t = c - R c, metres) and
        continuous [(axis [3] unit, offset [3] m, a point on the axis)]. A continuous axis (every
        rotation by multiples of 10 deg passes) is reported once, without its discrete rotations;
        with a continuous axis only one 180 deg flip about a perpendicular axis is listed (the
        continuous rotations generate the others). Without one, the discrete set is closed under
        composition.
    """
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) < 4:
        raise ValueError(f"vertices must be [N,3] with N >= 4, got {V.shape}")
    C = None
    if colors is not None:
        C = np.asarray(colors, dtype=np.float64)
        if C.shape != V.shape:
            raise ValueError(f"colors must be [N,3] like vertices {V.shape}, got {C.shape}")
    c = (V.min(axis=0) + V.max(axis=0)) / 2.0 if centre is None else np.asarray(centre, dtype=np.float64).reshape(3)
    checker = _Checker(V, symmetry_tolerance(diameter), C, colour_threshold, max_points)
    frames = (
        candidate_frames(V) if axes is None else [np.array([np.asarray(a, dtype=np.float64) / np.linalg.norm(a) for a in axes])]
    )
    best: tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]] = (np.zeros((0, 4, 4)), [])
    for F in frames:
        found = _search_axes(list(F), c, checker)
        if (len(found[1]), len(found[0])) > (len(best[1]), len(best[0])):
            best = found
    return best


def _search_axes(
    axes: list[np.ndarray], c: np.ndarray, checker: _Checker
) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Symmetries among rotations about ``axes`` through ``c`` (see :func:`find_symmetries`)."""
    # Continuous: every rotation by a multiple of 10 deg passes; angles nearest 180 deg first (they
    # move points the most, so non-symmetric axes fail early).
    # Each angle and its negative are tested, so one direction per angle is the symmetric test.
    n_sweep = int(round(360.0 / CONTINUOUS_STEP_DEG))
    order = sorted(range(1, n_sweep), key=lambda k: (abs(k - n_sweep / 2), k))
    continuous: list[tuple[np.ndarray, np.ndarray]] = []
    for a in axes:
        if all(checker.directed(_about(a, 2.0 * math.pi * k / n_sweep, c)) for k in order):
            continuous.append((a.copy(), c.copy()))

    discrete = []
    if continuous:
        axis0 = continuous[0][0]
        for a in axes:
            if abs(float(a @ axis0)) < math.sin(math.radians(5.0)) and checker.symmetric(T := _about(a, math.pi, c)):
                discrete.append(T)
                break
    else:
        for a in axes:
            for angle in _discrete_angles():
                T = _about(a, angle, c)
                if not any(_same(T, D) for D in discrete) and checker.symmetric(T):
                    discrete.append(T)
        discrete = _close_group(discrete, checker) if discrete else []
    out = np.array(discrete).reshape(-1, 4, 4)
    out[np.abs(out) < 1e-12] = 0.0  # sin(pi) etc.: exact zeros read better in models_info.json
    return out, continuous


# how a start pose is judged (cosy-lite score-start, the coarse scorer's validation): right within
# WITHIN_DEG of GT, flipped beyond FLIPPED_DEG
WITHIN_DEG = 30.0
FLIPPED_DEG = 150.0


def rotation_errors_deg(R: np.ndarray, R_gt: np.ndarray, symmetries: np.ndarray) -> np.ndarray:
    """``[N]`` angles (deg) between each ``R [N,3,3]`` and the closest of ``R_gt @ S`` over the
    object's symmetry rotations ``symmetries [S,3,3]`` (identity included)."""
    equivalent = R_gt[None] @ symmetries  # [S,3,3]
    trace = np.einsum("nij,sij->ns", R, equivalent)
    return np.degrees(np.arccos(np.clip((trace - 1) / 2, -1.0, 1.0))).min(axis=1)

"""Depth ICP: refine object poses against a measured depth image (Open3D point-to-plane ICP).

Per object (the objects of an image are rendered in a few batched calls, by window size):

1. window: the projected box of the model's 8 bounding-box corners at the current pose, united
   with the box of the object's mask, widened by ``cfg.window_margin`` px, clipped to the image;
2. pixels: every :func:`pixel_stride`-th one of the window, about 2 per voxel side at the
   object's depth, so near objects cost no more than far ones;
3. source: the model's depth rendered at the current pose at those pixels only (the window's
   intrinsics, scaled by 1 / stride), back-projected to camera-frame points: the visible model
   surface, which moves with the pose. Rendered pixels hidden by something else (outside the
   mask, measured depth in front by more than ``cfg.occlusion_margin``) are dropped;
4. target: the measured depth at those pixels inside the mask, back-projected; normals estimated
   with a hybrid k-d tree search; both voxel-downsampled; optionally the source
   is first moved along the object's viewing ray by the median depth difference (robust depth
   pre-alignment); then point-to-plane ICP with a robust kernel over a coarse -> fine schedule
   of correspondence distances, in the camera frame moved to the object origin (turns about the
   object stay turns about the object);
5. the camera-frame update ``T`` (source -> target) gives ``TCO_new = T @ TCO`` (with a symmetry
   set given, its symmetric equivalent closest in rotation to the start); the result is
   rejected (input pose returned, ``accepted=False`` and a reason) when either cloud is too small,
   the update is not finite, rotates or moves the object more than the limits, or the final
   fitness / inlier RMSE fail their limits (all off by default), or
6. (``check_agreement``, default) its rendered depth agrees with the measured depth less than its
   start's (:func:`depth_agreement`: the VSD criterion with the mask standing in for the unknown GT;
   one more batched render, of the results, both compared at the pixels of step 2).

Units: metres, depth 0 (or non-finite) = no measurement. Pixel convention as the renderer: pixel
(row r, column c) is the ray through ``(u, v) = (c + 0.5, r + 0.5)``. Nothing outside the windows
is touched per object (only the mask's bounding box is found with two ``any`` reductions).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from cosy_lite.geometry.depth import mask_box as mask_box_of

if TYPE_CHECKING:
    import open3d as o3d
    import trimesh

    from cosy_lite.render.renderer import MeshRenderer


@dataclass
class IcpConfig:
    """Depth ICP settings (metres, degrees); defaults for YCB-V-sized objects 0.5-1.5 m away.

    By default every result is kept only if its depth agrees with the measurement at least as well
    as its start's (``check_agreement``), and the limits on the update are off: on the demo's test
    split (GT masks, template starts, bench/RESULTS.md issue 13) the 15 deg / 5 cm / fitness / RMSE
    limits of the first version rejected 70 % of the updates (522 of 811 by 15 deg) and gave AR 0.306; without them, with
    the agreement check and a 4 cm first stage, AR 0.541. With ``check_agreement=False`` set limits
    (e.g. ``max_rotation_deg=15 max_translation=0.05 min_fitness=0.5 max_inlier_rmse=0.004``).
    """

    # m, per stage; three stages against four (4, 2, 1, 0.5 cm): ICP 9-19 % faster, AR within 0.001 on
    # the test and val splits; two (4, 0.8 cm) lost 0.007 (bench/RESULTS.md, session 33)
    max_correspondence_distances: list[float] = field(default_factory=lambda: [0.04, 0.015, 0.005])
    iterations: list[int] = field(default_factory=lambda: [10, 10, 10])  # ICP iterations per stage, at most
    # a stage ends early when fitness and inlier RMSE change by less than this fraction in an iteration
    # (Open3D's relative_fitness / relative_rmse); 1e-4 against 1e-6: ICP 11-15 % faster at the same AR (bench/RESULTS.md)
    relative_tolerance: float = 1e-4
    robust_kernel: str = "tukey"  # key of ROBUST_KERNELS
    robust_k: float | None = None  # kernel scale (m); None: each stage's correspondence distance
    voxel_size: float = 0.004  # m, voxel grid of both clouds
    normal_radius: float = 0.010  # m, target normals: hybrid search radius ...
    normal_max_nn: int = 20  # ... and most neighbours
    min_points: int = 50  # fewest points in either downsampled cloud
    window_margin: int = 16  # px around the projected model box and the mask box
    occlusion_margin: float = 0.02  # m, rendered pixel outside the mask, measured this much in front: hidden
    depth_prealign: bool = True  # move along the object's ray by the median depth difference before ICP
    max_rotation_deg: float = 180.0  # reject updates rotating the object more (180: no limit)
    max_translation: float = 1.0  # m, reject updates moving the object origin more
    min_fitness: float = 0.0  # least fraction of model points with a measured one within the last distance
    max_inlier_rmse: float = 1.0  # m, largest RMSE of those correspondences
    # keep an ICP result only when its rendered depth agrees with the measured depth at least as well
    # as its start's (:func:`depth_agreement`): a check on the result itself, beside the limits above
    check_agreement: bool = True
    agreement_tolerance: float = 0.02  # m, rendered and measured depth agree within this
    # the Predictor, with several start candidates per object (templates, K > 1): ICP each and keep
    # the one whose depth agrees best (needs check_agreement); False: only the candidate the RGB pipeline chose
    verify_candidates: bool = True
    # ... the others are tried only where the chosen one's agreement after ICP is below this (above 1:
    # always). Measured (GT masks, 4 candidates, 100 test images): 0.99 spares 34 % of the detections
    # the others' ICP at the same AR (0.7227 / 0.7229); 0.97 spares 51 % at AR 0.710; a detector's
    # masks never reach 0.99 (at most 0.94 there: their edges are not exact) (bench/RESULTS.md)
    accept_agreement: float = 0.99

    def __post_init__(self) -> None:
        if len(self.max_correspondence_distances) != len(self.iterations) or not self.iterations:
            raise ValueError(
                f"IcpConfig: max_correspondence_distances {list(self.max_correspondence_distances)} and iterations "
                f"{list(self.iterations)} must be non-empty and of the same length (one entry per stage)"
            )
        if self.robust_kernel not in ROBUST_KERNELS:
            raise ValueError(f"IcpConfig.robust_kernel: unknown {self.robust_kernel!r}; known: {sorted(ROBUST_KERNELS)}")
        if min(self.max_correspondence_distances) <= 0 or self.voxel_size <= 0 or self.normal_radius <= 0:
            raise ValueError("IcpConfig: distances, voxel_size and normal_radius must be > 0")
        if not 0 <= self.relative_tolerance < 1:
            raise ValueError(f"IcpConfig.relative_tolerance must be in [0, 1), got {self.relative_tolerance}")


@dataclass
class IcpResult:
    """Outcome of one object's ICP.

    TCO: [4,4] refined pose (m), or the input pose when not accepted; reason: why rejected ("" if
    accepted); fitness: fraction of model points with a measured point within the last stage's
    distance; inlier_rmse (m) of those; n_points / n_model_points: measured / model points after
    downsampling; delta_rotation_deg, delta_translation (m): the update ICP proposed (NaN if none);
    agreement: :func:`depth_agreement` of ``TCO`` with ``cfg.check_agreement`` (-1 otherwise);
    seconds: this object's cost (its share of the batched render + its own clouds, normals, ICP,
    agreement check), broken down in ``timings`` (render, clouds, normals, icp, agreement).
    """

    TCO: np.ndarray
    accepted: bool
    reason: str = ""
    fitness: float = 0.0
    inlier_rmse: float = float("nan")
    n_points: int = 0
    n_model_points: int = 0
    delta_rotation_deg: float = float("nan")
    delta_translation: float = float("nan")
    agreement: float = -1.0  # depth_agreement of the returned pose (-1: not computed)
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)


LIMITS = ("max_rotation_deg", "max_translation", "min_fitness", "max_inlier_rmse")  # IcpConfig's acceptance limits


def icp_rejection_kind(reason: str) -> str:
    """A short class of an :attr:`IcpResult.reason`, for counting: the limit it names, else its
    words before the first number or parenthesis (e.g. "too few measured depth points in the mask")."""
    for name in LIMITS:
        if name in reason:
            return name
    return re.split(r"[\d(]", reason, maxsplit=1)[0].strip() or "unknown"


# name -> robust kernel class of open3d.pipelines.registration, each with a scale k (m)
ROBUST_KERNELS = {"tukey": "TukeyLoss", "huber": "HuberLoss", "cauchy": "CauchyLoss"}


def robust_kernel(name: str, k: float) -> Any:
    """The Open3D robust kernel ``name`` (a key of ROBUST_KERNELS) with scale ``k`` (m)."""
    import open3d as o3d

    return getattr(o3d.pipelines.registration, ROBUST_KERNELS[name])(k=k)


# ----------------------------------------------------------------------------- geometry helpers


def backproject(rows: np.ndarray, cols: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points [N,3] (m) of pixels (rows, cols) [N] with depth z [N] (m), image intrinsics K [3,3]."""
    yn = (rows + 0.5 - K[1, 2]) / K[1, 1]
    xn = (cols + 0.5 - K[0, 2] - K[0, 1] * yn) / K[0, 0]
    z = z.astype(np.float64)
    return np.stack([xn * z, yn * z, z], axis=1)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle (deg) of a rotation matrix [3,3]."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def pixel_stride(voxel_size: float, K: np.ndarray, z: float) -> int:
    """Pixel step keeping at least ~2 samples per voxel side at depth z (m): max(1, voxel fx / (2 z))."""
    return max(1, int(voxel_size * min(K[0, 0], K[1, 1]) / (2.0 * max(z, 1e-6))))


def _box_corners(mesh: trimesh.Trimesh) -> np.ndarray:
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def _window(TCO: np.ndarray, K: np.ndarray, corners: np.ndarray, mask_box: tuple[int, int, int, int] | None,
            size: tuple[int, int], margin: int) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) px, half-open, in the image: projected model box U mask box, widened; None if empty."""
    H, W = size
    p = corners @ TCO[:3, :3].T + TCO[:3, 3]
    if (p[:, 2] <= 1e-3).any():  # the box reaches behind the camera: its projection is unbounded
        box = [0.0, 0.0, float(W), float(H)]
    else:
        uv = p @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        box = [uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()]
    if mask_box is not None:
        box = [min(box[0], mask_box[0]), min(box[1], mask_box[1]), max(box[2], mask_box[2]), max(box[3], mask_box[3])]
    x0 = int(np.clip(np.floor(box[0]) - margin, 0, W))
    y0 = int(np.clip(np.floor(box[1]) - margin, 0, H))
    x1 = int(np.clip(np.ceil(box[2]) + margin, 0, W))
    y1 = int(np.clip(np.ceil(box[3]) + margin, 0, H))
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1)


def _cloud(points: np.ndarray, voxel_size: float) -> o3d.geometry.PointCloud:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return pcd.voxel_down_sample(voxel_size)


# ----------------------------------------------------------------------------- checks


def _inputs(TCO: Any, K: Any, depth: Any, masks: Any, obj_ids: Sequence[int]) -> tuple:
    """(TCO [N,4,4] float64, K [3,3] float64, depth [H,W], masks [N,H,W] bool, obj_ids list[int]), checked."""
    TCO = np.asarray(TCO, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    depth = np.asarray(depth)
    masks = np.asarray(masks).astype(bool, copy=False)
    obj_ids = [int(i) for i in obj_ids]
    _check_inputs(TCO, K, depth, masks, obj_ids)
    return TCO, K, depth, masks, obj_ids


def _render_windows(renderer: MeshRenderer, obj_ids: Sequence[int], TCO: np.ndarray, K: np.ndarray,
                    windows: Mapping[int, tuple[int, int, int, int]], todo: list[int],
                    strides: Mapping[int, int] | None = None) -> list[np.ndarray]:
    """Model depth of objects ``todo`` in their windows (x0, y0, x1, y1), every ``strides[i]``-th
    pixel (default 1): per object an array whose top-left part of :func:`_strided_shape` is its
    window, sampled as ``depth[y0:y1:s, x0:x1:s]`` would be. Windows of similar size share a batched
    render at their largest size (a window's canvas is at most twice its own area): one batch at the
    largest window's size drew 3.5x the windows' pixels on the demo's images."""
    step = {i: 1 if strides is None else int(strides[i]) for i in todo}
    size = {i: _strided_shape(windows[i], step[i]) for i in todo}
    groups: list[list[int]] = []
    canvas = (0, 0)
    for i in sorted(todo, key=lambda i: size[i][0] * size[i][1], reverse=True):
        h, w = size[i]
        grown = (max(canvas[0], h), max(canvas[1], w))
        if groups and grown[0] * grown[1] <= 2 * h * w:
            groups[-1].append(i)
            canvas = grown
        else:
            groups.append([i])
            canvas = (h, w)
    out: dict[int, np.ndarray] = {}
    for group in groups:
        h = max(size[i][0] for i in group)
        w = max(size[i][1] for i in group)
        depth = renderer.render([obj_ids[i] for i in group], TCO[group],
                                np.stack([_window_intrinsics(K, windows[i], step[i]) for i in group]), (h, w),
                                depth_only=True).depth
        out.update(zip(group, depth))
    return [out[i] for i in todo]


def _strided_shape(window: tuple[int, int, int, int], stride: int) -> tuple[int, int]:
    """(rows, columns) of ``image[y0:y1:stride, x0:x1:stride]``."""
    x0, y0, x1, y1 = window
    return -(-(y1 - y0) // stride), -(-(x1 - x0) // stride)


def _window_intrinsics(K: np.ndarray, window: tuple[int, int, int, int], stride: int) -> np.ndarray:
    """Intrinsics whose pixel (r, c) is the ray of the image's pixel ``(y0 + stride r, x0 + stride c)``:
    the crop of :func:`~cosy_lite.geometry.crops.crop_intrinsics` whose pixel ``c`` samples the image at
    ``u = x0 + stride c + 0.5`` (rays through pixel centres)."""
    import torch

    from cosy_lite.geometry.crops import crop_intrinsics

    x0, y0 = window[:2]
    h, w = _strided_shape(window, stride)
    left, top = x0 + 0.5 - 0.5 * stride, y0 + 0.5 - 0.5 * stride
    box = torch.tensor([[left, top, left + w * stride, top + h * stride]], dtype=torch.float64)
    return crop_intrinsics(torch.as_tensor(K, dtype=torch.float64)[None], box, (h, w))[0].numpy()


def _check_inputs(TCO: np.ndarray, K: np.ndarray, depth: np.ndarray, masks: np.ndarray, obj_ids: Sequence[int]) -> None:
    N = len(obj_ids)
    if TCO.shape != (N, 4, 4):
        raise ValueError(f"TCO must be [N,4,4] with N = len(obj_ids) = {N}, got shape {TCO.shape}")
    bad = np.flatnonzero(~np.isfinite(TCO).all(axis=(1, 2)))
    if len(bad):
        raise ValueError(f"TCO is not finite (NaN/inf) at index {bad.tolist()}")
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite [3,3] with fx, fy > 0, got shape {K.shape}")
    if depth.ndim != 2:
        raise ValueError(f"depth_measured must be [H,W] (m), got shape {depth.shape}")
    if masks.shape != (N, *depth.shape):
        raise ValueError(f"masks must be [N,H,W] = {(N, *depth.shape)} (one per object, as depth_measured), got {masks.shape}")


# ----------------------------------------------------------------------------- ICP


def refine_poses_icp(
    TCO: np.ndarray, K: np.ndarray, depth_measured: np.ndarray, masks: np.ndarray,
    renderer: MeshRenderer, obj_ids: Sequence[int], cfg: IcpConfig | None = None,
    symmetries: Sequence[np.ndarray | None] | None = None,
) -> list[IcpResult]:
    """Refine the N object poses of one image against its measured depth.

    Args:
        TCO: [N,4,4] object-to-camera poses (m); K: [3,3] image intrinsics;
        depth_measured: [H,W] camera z (m), 0 or non-finite = unknown;
        masks: [N,H,W] bool, each object's (visible / detection) mask in the full image;
        renderer: renders the models (``render(..., depth_only=True)`` and ``mesh(obj_id)``);
        obj_ids: [N]; cfg: :class:`IcpConfig` (defaults if None);
        symmetries: optional, per object its symmetry set [S,4,4] (model frame, m, e.g.
            :func:`cosy_lite.geometry.symmetries.symmetry_transforms`) or None: the refined pose is
            replaced by its symmetric equivalent closest in rotation to the input, so a free turn
            about a symmetry axis (common: point-to-plane cannot see it) is neither reported nor
            counted against ``max_rotation_deg``.
    Returns: one :class:`IcpResult` per object, in order. Windows of similar size share one render call.
    Raises ValueError for wrong shapes or a non-finite TCO / K (naming the argument and index).
    """
    cfg = IcpConfig() if cfg is None else cfg
    TCO, K, depth, masks, obj_ids = _inputs(TCO, K, depth_measured, masks, obj_ids)
    N = len(obj_ids)
    if symmetries is not None and len(symmetries) != N:
        raise ValueError(f"symmetries must hold one [S,4,4] array (or None) per object: {len(symmetries)} for {N} objects")
    H, W = depth.shape
    t_start = time.perf_counter()
    results: list[IcpResult | None] = [None] * N
    windows: list[tuple[int, int, int, int] | None] = [None] * N
    for i in range(N):
        mask_box = mask_box_of(masks[i])
        if mask_box is None:
            results[i] = IcpResult(TCO[i].copy(), False, "empty mask")
        elif TCO[i, 2, 3] <= 0:
            results[i] = IcpResult(TCO[i].copy(), False, "object origin not in front of the camera (TCO z <= 0)")
        else:
            windows[i] = _window(TCO[i], K, _box_corners(renderer.mesh(obj_ids[i])), mask_box, (H, W), cfg.window_margin)
            if windows[i] is None:  # (not with a mask inside the image: its box is part of the window)
                results[i] = IcpResult(TCO[i].copy(), False, "no image window around the object")
    todo = {i: w for i, w in enumerate(windows) if w is not None}
    strides = {i: pixel_stride(cfg.voxel_size, K, TCO[i, 2, 3]) for i in todo}  # the pixels ICP samples
    rendered = _render_windows(renderer, obj_ids, TCO, K, todo, list(todo), strides) if todo else []
    render_share = (time.perf_counter() - t_start) / max(len(todo), 1)
    refined: dict[int, IcpResult] = {}
    for j, (i, window) in enumerate(todo.items()):
        syms = None if symmetries is None or symmetries[i] is None else np.asarray(symmetries[i], dtype=np.float64)
        refined[i] = _refine_one(TCO[i], K, depth, masks[i], rendered[j], window, cfg, syms)
        refined[i].timings["render"] = render_share
    done = [r if r is not None else refined[i] for i, r in enumerate(results)]
    if cfg.check_agreement:
        _check_agreement(done, {i: rendered[j] for j, i in enumerate(todo)}, strides, windows, TCO, K, depth, masks,
                         renderer, obj_ids, cfg)
    for r in refined.values():
        r.seconds = sum(r.timings.values())
    return done


def _check_agreement(results: list, rendered: dict[int, np.ndarray], strides: Mapping[int, int], windows: list,
                     TCO: np.ndarray, K: np.ndarray, depth: np.ndarray, masks: np.ndarray, renderer: MeshRenderer,
                     obj_ids: Sequence[int], cfg: IcpConfig) -> None:
    """Set each result's ``agreement`` and reject, in place, an accepted result whose depth agrees
    less than its start's (the starts' renders are those ICP made, every ``strides[i]``-th pixel; the
    results get batched renders, sampled alike)."""
    t0 = time.perf_counter()
    start = np.zeros(len(results))
    for i, r in rendered.items():
        start[i] = _window_agreement(r, depth, masks[i], windows[i], strides[i], cfg.agreement_tolerance)
    moved = [i for i, r in enumerate(results) if r.accepted]
    after = dict(zip(moved, depth_agreement(np.stack([results[i].TCO for i in moved]), K, depth, masks[moved], renderer,
                                            [obj_ids[i] for i in moved], cfg.agreement_tolerance, cfg.window_margin,
                                            cfg.voxel_size)
                     if moved else []))
    for i, r in enumerate(results):
        if i in after and after[i] < start[i]:
            results[i] = replace(r, TCO=TCO[i].copy(), accepted=False, agreement=float(start[i]),
                                 reason=f"ICP result agrees less with the depth than its start ({after[i]:.3f} < {start[i]:.3f})")
        else:
            r.agreement = float(after.get(i, start[i]))
    if rendered:
        share = (time.perf_counter() - t0) / len(rendered)
        for i in rendered:
            results[i].timings["agreement"] = share


def _window_agreement(rendered: np.ndarray, depth: np.ndarray, mask: np.ndarray, window: tuple[int, int, int, int],
                      stride: int, tolerance: float) -> float:
    """:func:`depth_agreement` in one window, every ``stride``-th pixel: ``rendered`` as
    :func:`_render_windows` gives it, the image's measured ``depth`` [H,W] (m, 0 = none) and ``mask`` [H,W]."""
    x0, y0, x1, y1 = window
    h, w = _strided_shape(window, stride)
    r = np.asarray(rendered[:h, :w], dtype=np.float64)
    m = np.asarray(depth[y0:y1:stride, x0:x1:stride], dtype=np.float64)
    in_mask = mask[y0:y1:stride, x0:x1:stride]
    known = (m > 0) & np.isfinite(m)
    drawn = r > 0
    seen = drawn & (~known | (r <= m + tolerance))
    agree = in_mask & drawn & (~known | (np.abs(r - m) <= tolerance))
    return float(agree.sum() / max(int((in_mask | seen).sum()), 1))


def depth_agreement(
    TCO: np.ndarray, K: np.ndarray, depth_measured: np.ndarray, masks: np.ndarray,
    renderer: MeshRenderer, obj_ids: Sequence[int], tolerance: float = 0.02, window_margin: int = 16,
    sample_spacing: float | None = None,
) -> np.ndarray:
    """``[N]`` in [0, 1]: how well each pose explains its object's mask and measured depth.

    Per object, over the window of :func:`refine_poses_icp` (projected model box U mask box): the
    pixels where the model, rendered at the pose, would be seen (drawn, and not behind the measured
    surface by more than ``tolerance``: that is an occluder) or the mask is, and of those the share
    where both are and the depths agree within ``tolerance`` (unknown depth in the mask: agrees).
    A pose whose model floats in front of the measured surface outside the mask, leaves part of
    the mask unexplained, or is turned so that its depth disagrees scores lower: the VSD criterion
    with the mask standing in for the unknown GT. 0 for an empty mask or a pose behind the camera.
    Args as :func:`refine_poses_icp` (masks [N,H,W] bool); windows of similar size share one render call.
    ``sample_spacing`` (m): only every :func:`pixel_stride` px is compared, the pixels ICP samples with
    that voxel size at the object's depth (about 2 per voxel side; a quarter of the pixels at 4 mm and
    1 m with YCB-V's camera); None: every pixel.
    """
    TCO, K, depth, masks, obj_ids = _inputs(TCO, K, depth_measured, masks, obj_ids)
    H, W = depth.shape
    scores = np.zeros(len(obj_ids))
    windows: dict[int, tuple[int, int, int, int]] = {}
    for i in range(len(obj_ids)):
        mask_box = mask_box_of(masks[i])
        if mask_box is not None and TCO[i, 2, 3] > 0:
            win = _window(TCO[i], K, _box_corners(renderer.mesh(obj_ids[i])), mask_box, (H, W), window_margin)
            if win is not None:
                windows[i] = win
    if not windows:
        return scores
    todo = sorted(windows)
    strides = {i: 1 if sample_spacing is None else pixel_stride(sample_spacing, K, TCO[i, 2, 3]) for i in todo}
    rendered = _render_windows(renderer, obj_ids, TCO, K, windows, todo, strides)
    for j, i in enumerate(todo):
        scores[i] = _window_agreement(rendered[j], depth, masks[i], windows[i], strides[i], tolerance)
    return scores


def refine_pose_icp(
    TCO: np.ndarray, K: np.ndarray, depth_measured: np.ndarray, mask: np.ndarray,
    renderer: MeshRenderer, obj_id: int, cfg: IcpConfig | None = None, symmetries: np.ndarray | None = None,
) -> IcpResult:
    """Refine one pose: TCO [4,4] (m), K [3,3], depth_measured [H,W] (m, 0 = unknown), mask [H,W] bool,
    optional symmetry set [S,4,4]. See :func:`refine_poses_icp`; returns the refined pose, or the
    input pose with the reason."""
    masks = np.asarray(mask)[None]
    return refine_poses_icp(np.asarray(TCO)[None], K, depth_measured, masks, renderer, [obj_id], cfg, [symmetries])[0]


class _Rejected(Exception):
    """An object ICP cannot refine: the reason and what was counted."""

    def __init__(self, reason: str, **counts: int):
        super().__init__(reason)
        self.reason, self.counts = reason, counts


def _refine_one(
    TCO: np.ndarray, K: np.ndarray, depth: np.ndarray, mask: np.ndarray, rendered: np.ndarray,
    window: tuple[int, int, int, int], cfg: IcpConfig, symmetries: np.ndarray | None,
) -> IcpResult:
    """ICP of one object whose model depth ``rendered`` starts at the window's corner, every
    :func:`pixel_stride`-th pixel (:func:`_render_windows`)."""
    import open3d as o3d

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    try:
        source, target, T_init = _object_clouds(TCO, K, depth, mask, rendered, window, cfg)
    except _Rejected as r:
        timings["clouds"] = time.perf_counter() - t0
        return IcpResult(TCO.copy(), False, r.reason, timings=timings, **r.counts)
    n_tgt, n_src = len(target.points), len(source.points)
    timings["clouds"] = time.perf_counter() - t0
    target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius, max_nn=cfg.normal_max_nn))
    target.orient_normals_towards_camera_location(np.zeros(3))
    timings["normals"] = time.perf_counter() - t0 - timings["clouds"]
    T, fitness, inlier_rmse = _register(source, target, T_init, cfg)
    timings["icp"] = time.perf_counter() - t0 - timings["clouds"] - timings["normals"]
    stats: dict[str, Any] = dict(n_points=n_tgt, n_model_points=n_src, fitness=fitness, inlier_rmse=inlier_rmse,
                                 timings=timings)
    if not np.isfinite(T).all():
        return IcpResult(TCO.copy(), False, "ICP update is not finite", **stats)
    c = TCO[:3, 3]
    T[:3, 3] += c - T[:3, :3] @ c  # camera frame: C T C^-1, C = translation by c
    TCO_new = T @ TCO
    if symmetries is not None:  # the symmetric equivalent closest in rotation to the input pose
        candidates = TCO_new @ symmetries
        cos = np.einsum("sij,ij->s", candidates[:, :3, :3], TCO[:3, :3])  # trace(R_s^T R) = 1 + 2 cos(angle)
        TCO_new = candidates[int(np.argmax(cos))]
    d_rot = rotation_angle_deg(TCO_new[:3, :3] @ TCO[:3, :3].T)
    d_trans = float(np.linalg.norm(TCO_new[:3, 3] - TCO[:3, 3]))
    stats.update(delta_rotation_deg=d_rot, delta_translation=d_trans)
    checks = [
        (d_rot > cfg.max_rotation_deg, f"update rotates {d_rot:.1f} deg > max_rotation_deg {cfg.max_rotation_deg}"),
        (d_trans > cfg.max_translation,
         f"update moves {d_trans * 1000:.1f} mm > max_translation {cfg.max_translation * 1000:.0f} mm"),
        (fitness < cfg.min_fitness, f"fitness {fitness:.3f} < min_fitness {cfg.min_fitness}"),
        (inlier_rmse > cfg.max_inlier_rmse,
         f"inlier RMSE {inlier_rmse * 1000:.2f} mm > max_inlier_rmse {cfg.max_inlier_rmse * 1000:.1f} mm"),
    ]
    for failed, reason in checks:
        if failed:
            return IcpResult(TCO.copy(), False, reason, **stats)
    return IcpResult(TCO_new, True, "", **stats)


def _object_clouds(TCO: np.ndarray, K: np.ndarray, depth: np.ndarray, mask: np.ndarray, rendered: np.ndarray,
                   window: tuple[int, int, int, int], cfg: IcpConfig) -> tuple[Any, Any, np.ndarray]:
    """(model cloud, measured cloud, initial transform [4,4]) of one object in the object-centred
    camera frame (origin at the object origin: ICP's rotations turn about the object, so a turn about
    a symmetry axis, free for point-to-plane, is not coupled to a translation that the small-angle
    solve would get wrong for large angles). Raises _Rejected when either cloud is too small."""
    x0, y0, x1, y1 = window
    s = pixel_stride(cfg.voxel_size, K, TCO[2, 3])
    h, w = _strided_shape(window, s)
    d_model = rendered[:h, :w]
    d_meas = depth[y0:y1:s, x0:x1:s]
    meas_ok = (d_meas > 0) & (d_meas < np.inf)
    m = mask[y0:y1:s, x0:x1:s]
    model_ok = d_model > 0
    hidden = model_ok & ~m & meas_ok & (d_meas < d_model - cfg.occlusion_margin)
    src_px = model_ok & ~hidden
    tgt_px = m & meas_ok
    n_tgt, n_src = int(tgt_px.sum()), int(src_px.sum())
    if n_tgt < cfg.min_points:
        raise _Rejected(f"too few measured depth points in the mask ({n_tgt} < {cfg.min_points})", n_points=n_tgt)
    if n_src < cfg.min_points:
        raise _Rejected(f"too few rendered model points in the window ({n_src} < {cfg.min_points})", n_model_points=n_src)
    T_init = np.eye(4)
    if cfg.depth_prealign:
        both = model_ok & tgt_px
        if both.sum() >= cfg.min_points:
            dz = float(np.median(d_meas[both] - d_model[both]))
            T_init[:3, 3] = TCO[:3, 3] * dz / TCO[2, 3]  # along the ray through the object origin
    c = TCO[:3, 3]
    rows, cols = np.nonzero(tgt_px)
    target = _cloud(backproject(s * rows + y0, s * cols + x0, d_meas[rows, cols], K) - c, cfg.voxel_size)
    rows, cols = np.nonzero(src_px)
    source = _cloud(backproject(s * rows + y0, s * cols + x0, d_model[rows, cols], K) - c, cfg.voxel_size)
    n_tgt, n_src = len(target.points), len(source.points)
    if min(n_tgt, n_src) < cfg.min_points:
        raise _Rejected(f"too few points after downsampling (measured {n_tgt}, model {n_src}; need {cfg.min_points})",
                        n_points=n_tgt, n_model_points=n_src)
    return source, target, T_init


def _register(source: Any, target: Any, T_init: np.ndarray, cfg: IcpConfig) -> tuple[np.ndarray, float, float]:
    """(transform [4,4], fitness, inlier RMSE) of the staged point-to-plane ICP of ``source`` onto ``target``."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    T, fitness, inlier_rmse = T_init, 0.0, 0.0  # (a translation: the same in both frames)
    for dist, iters in zip(cfg.max_correspondence_distances, cfg.iterations):
        kernel = robust_kernel(cfg.robust_kernel, dist if cfg.robust_k is None else cfg.robust_k)
        result = reg.registration_icp(
            source, target, dist, T, reg.TransformationEstimationPointToPlane(kernel),
            reg.ICPConvergenceCriteria(relative_fitness=cfg.relative_tolerance, relative_rmse=cfg.relative_tolerance,
                                       max_iteration=int(iters)),
        )
        T, fitness, inlier_rmse = np.array(result.transformation), float(result.fitness), float(result.inlier_rmse)
    return T, fitness, inlier_rmse

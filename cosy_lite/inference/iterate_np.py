"""The render-and-compare loop of the onnxruntime path, in numpy: no torch op per iteration.

Twin of :func:`cosy_lite.models.render_and_compare.iterate_poses` for one image: crop boxes from the
current poses (:func:`cosy_lite.geometry.crops_np.crop_boxes`), the image crops (``roi_align``'s
sampling in numpy, :func:`~cosy_lite.geometry.crops_np.crop_image`) and ``K_crop``, the objects
rendered with ``K_crop`` (:meth:`Renderer.render`, numpy out), the ``[B,6,h,w]`` float32 input
(crop, rendering) -> a numpy network (:meth:`cosy_lite.export.onnx_models.OnnxPoseNet.run`) ->
:func:`cosy_lite.models.pose_update_np.apply_pose_update` (9-number networks) or
:func:`cosy_lite.models.flow_pose_solver_np.pose_from_flow` (flow networks, with the rendering's depth). Poses are float64 throughout. Pose
checks (:func:`valid_poses`, :func:`orthonormalise`) are here too. Imports numpy only (the
renderer is passed in), so the loop runs where torch is not installed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from cosy_lite.geometry.crops_np import crop_boxes, crop_image, crop_intrinsics
from cosy_lite.models.flow_pose_solver_np import FLOW_STRIDE, flow_confidence, pose_from_flow
from cosy_lite.models.pose_update_np import apply_pose_update

Size = tuple[int, int]
NumpyNet = Callable[[np.ndarray], np.ndarray]  # [B,6,h,w] float32 in [0, 1] -> [B,9]
MIN_DEPTH = 0.02  # m: an estimate nearer than this (or behind the camera) is invalid (BOP: t >= 20 mm)


@dataclass
class NetInputs:
    """images [B,6,h,w] float32 in [0, 1] (image crop, rendering); K_crop [B,3,3] float64; boxes [B,4]
    float64 xyxy px; depth [B,h,w] (m, 0 off the object) of the rendering."""

    images: np.ndarray
    K_crop: np.ndarray
    boxes: np.ndarray
    depth: np.ndarray


def image_array(rgb: np.ndarray) -> np.ndarray:
    """``rgb [H,W,3]`` uint8 -> ``[H,W,3]`` float32 in [0, 1] (what :func:`make_inputs` crops)."""
    return rgb.astype(np.float32) / np.float32(255.0)


def make_inputs(image: np.ndarray, K: np.ndarray, TCO: np.ndarray, obj_ids: Sequence[int], points: np.ndarray,
                renderer: Any, crop_resolution: Size) -> NetInputs:
    """Network inputs for objects at ``TCO [B,4,4]`` (m) in one ``image [H,W,3]`` (float32, [0, 1]).

    ``K [B,3,3]`` full-image intrinsics; ``points [B,N,3]`` model points (m) that set the crop
    size; ``renderer``: a :class:`~cosy_lite.render.renderer.Renderer` (its numpy :meth:`render`).
    """
    h, w = (int(v) for v in crop_resolution)
    boxes = crop_boxes(TCO, K, points, crop_resolution=(h, w))
    K_crop = crop_intrinsics(K, boxes, (h, w))
    images = np.empty((len(TCO), 6, h, w), dtype=np.float32)
    crop_image(image, boxes, (h, w), out=images[:, :3])
    rendered = renderer.render([int(i) for i in obj_ids], TCO, K_crop, (h, w))
    images[:, 3:] = rendered.rgb.transpose(0, 3, 1, 2)  # [B,h,w,3] uint8
    images[:, 3:] /= np.float32(255.0)
    return NetInputs(images, K_crop, boxes, rendered.depth)


def updated_poses(TCO: np.ndarray, inp: NetInputs, out: np.ndarray, output: str = "delta") -> np.ndarray:
    """The poses after the network answered ``out`` (``[B,9]`` updates or a ``[B,3,h,w]`` flow field)."""
    if output == "flow":
        return pose_from_flow(TCO, inp.K_crop, inp.depth, out, FLOW_STRIDE)
    return apply_pose_update(TCO, inp.K_crop, out)


def iterate_poses(net: NumpyNet, image: np.ndarray, K: np.ndarray, TCO_init: np.ndarray, obj_ids: Sequence[int],
                  points: np.ndarray, renderer: Any, n_iterations: int, crop_resolution: Size,
                  batch_size: int = 32, output: str = "delta") -> list[np.ndarray]:
    """``n_iterations`` render-and-compare updates from ``TCO_init [B,4,4]`` (m) in one ``image``;
    the poses after each iteration (float64 ``[B,4,4]`` each). Arguments as :func:`make_inputs`;
    ``net`` maps ``[b,6,h,w]`` float32 to ``[b,9]`` (``output="delta"``) or to a flow field
    (``"flow"``); ``batch_size`` items per network call."""
    poses, TCO = [], np.asarray(TCO_init, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    for _ in range(n_iterations):
        out = []
        for s in range(0, len(TCO), batch_size):
            sl = slice(s, s + batch_size)
            inp = make_inputs(image, K[sl], TCO[sl], obj_ids[sl], points[sl], renderer, crop_resolution)
            out.append(updated_poses(TCO[sl], inp, net(inp.images), output))
        TCO = np.concatenate(out) if out else TCO
        poses.append(TCO)
    return poses


def refine_and_score(net: NumpyNet, image: np.ndarray, K: np.ndarray, TCO: np.ndarray, obj_ids: Sequence[int],
                     points: np.ndarray, renderer: Any, crop_resolution: Size,
                     batch_size: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """One iteration of a flow network from ``TCO [B,4,4]``: (poses, confidence ``[B]``). Twin of
    :func:`cosy_lite.models.render_and_compare.refine_and_score`."""
    TCO, K, points = (np.asarray(a, dtype=np.float64) for a in (TCO, K, points))
    poses, scores = [], []
    for s in range(0, len(TCO), batch_size):
        sl = slice(s, s + batch_size)
        inp = make_inputs(image, K[sl], TCO[sl], obj_ids[sl], points[sl], renderer, crop_resolution)
        out = net(inp.images)
        poses.append(updated_poses(TCO[sl], inp, out, "flow"))
        scores.append(flow_confidence(inp.depth, out, FLOW_STRIDE))
    if not poses:
        return TCO, np.zeros(0)
    return np.concatenate(poses), np.concatenate(scores)


def valid_poses(TCO: np.ndarray, rotation_tol: float = 1e-3, min_depth: float = MIN_DEPTH) -> np.ndarray:
    """``[N]`` bool: ``TCO [N,4,4]`` finite, ``R`` orthonormal with det +1 (within ``rotation_tol``),
    z >= ``min_depth`` (m). As :func:`cosy_lite.inference.predictor.valid_poses`."""
    TCO = np.asarray(TCO, dtype=np.float64)
    finite = np.isfinite(TCO).all(axis=(1, 2))
    R = np.where(finite[:, None, None], TCO[:, :3, :3], np.eye(3))
    ortho = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2), initial=0.0) <= rotation_tol
    det = np.abs(np.linalg.det(R) - 1.0) <= rotation_tol
    return finite & ortho & det & (np.nan_to_num(TCO[:, 2, 3], nan=-1.0) >= min_depth)


def orthonormalise(TCO: np.ndarray) -> np.ndarray:
    """``TCO [N,4,4]`` float64 with each finite rotation replaced by the nearest rotation (SVD).
    As :func:`cosy_lite.inference.predictor.orthonormalise`."""
    TCO = np.array(TCO, dtype=np.float64)
    ok = np.isfinite(TCO).all(axis=(1, 2))
    if ok.any():
        U, _, Vh = np.linalg.svd(TCO[ok, :3, :3])
        D = np.ones((int(ok.sum()), 3))
        D[:, 2] = np.sign(np.linalg.det(U @ Vh))
        TCO[ok, :3, :3] = (U * D[:, None, :]) @ Vh
    return TCO

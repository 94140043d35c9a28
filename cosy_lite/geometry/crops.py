"""Pose-aware crops (CosyPose / DeepIM style) and the intrinsics of a crop (torch, batched).

Pixel convention (the project's: :mod:`cosy_lite.render.gl`, the renderers, ``bop/gt_info.py``, the
BOP toolkit): pixel (row r, column c) is the sample at ``(u, v) = (c + 0.5, r + 0.5)`` of the
projection ``u = fx X/Z + cx``, so pixel ``i`` covers ``[i, i+1)`` in ``u``. Projections, boxes
``[x1, y1, x2, y2]`` (a BOP box ``[x, y, w, h]`` is ``[x, y, x+w, y+h]``) and the coordinates of
``torchvision.ops.roi_align(aligned=True)`` are then the same numbers: output pixel ``j`` of a crop
of width ``w`` samples the image at ``u = x1 + (j + 0.5) s``, ``s = (x2 - x1) / w``, which is where
the crop's own pixel ``j`` lies under ``K_crop`` (:func:`crop_intrinsics`, ``u' = (u - x1) / s``).
So a crop of a rendered image and a render made with ``K_crop`` agree exactly. (Cameras calibrated
with OpenCV put pixel centres at integer ``u``; with such images the renders, hence the whole
pipeline, are half a pixel off, a matter for the renderer.)

CosyPose (``lib3d/cropping.py: deepim_boxes``, ``models/pose.py: crop_inputs``) builds the crop
from the current pose only: the box of the model points projected at the current pose, centred
on the projected object origin, half-extent ``max(dx, dy * r) * lambda`` (``lambda = 1.4``). Its
``obs_boxes`` argument is also that rendered box (the detection/GT box is not used). Differences
here: the aspect ratio ``r`` is the crop's (CosyPose uses the full image's, the same 4:3 for
640x480 images); ``roi_align`` is ``aligned=True`` with the K rewrite above (CosyPose: ``aligned=False``
and a K rewrite for pixel centres at integer ``u``); ``extra_boxes`` optionally widens the box to
contain another box (e.g. a detection).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from typing import Callable, cast

import torch
from torch import Tensor
from torchvision.ops import roi_align

Size = tuple[int, int]  # (height, width) in pixels

CROP_RESOLUTION: Size = (240, 320)  # CosyPose's render_size (h, w): 4:3
MARGIN = 1.4  # CosyPose's lambda
Z_MIN = 0.1  # m: points nearer than this are projected as if at this depth (CosyPose's project_points_robust)
SAMPLING_RATIO = 2  # roi_align samples per output pixel and axis (CosyPose: 4)


def _check(name: str, x: Tensor, shape: tuple) -> None:
    """Raise ValueError unless ``x`` has ``shape`` (``None`` = any size)."""
    ok = isinstance(x, Tensor) and x.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, x.shape))
    if not ok:
        want = "[" + ",".join("*" if s is None else str(s) for s in shape) + "]"
        got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"{name} must be a tensor of shape {want}, got {got}")


def project_points(TCO: Tensor, K: Tensor, points: Tensor, z_min: float = Z_MIN) -> Tensor:
    """Project object points ``[B,N,3]`` (m) at poses ``TCO [B,4,4]`` with ``K [B,3,3]``.

    Returns ``[B,N,2]`` image coordinates ``(u, v)`` (pixel ``i`` covers ``[i, i+1)``). Depths are
    clamped to ``>= z_min`` so points behind the camera give finite (meaningless) coordinates.
    """
    p = points @ TCO[:, :3, :3].transpose(1, 2) + TCO[:, None, :3, 3]
    p = p @ K.transpose(1, 2)
    return p[..., :2] / p[..., 2:3].clamp(min=z_min)


def crop_boxes(
    TCO: Tensor,
    K: Tensor,
    points: Tensor,
    *,
    crop_resolution: Size = CROP_RESOLUTION,
    margin: float = MARGIN,
    extra_boxes: Tensor | None = None,
    z_min: float = Z_MIN,
) -> Tensor:
    """Crop boxes ``[B,4]`` (x1, y1, x2, y2; image coordinates) for objects at poses ``TCO``.

    Centred on the projected object origin; half-width ``max(dx, r dy) * margin`` and half-height
    ``max(dx / r, dy) * margin``, ``r = w / h`` of ``crop_resolution`` (h, w), where ``dx``, ``dy``
    are the largest horizontal/vertical distances from the centre to a projected model point of
    ``points [B,N,3]`` (m) or to an edge of ``extra_boxes [B,4]`` if given. The image size plays
    no part (CosyPose took only its aspect ratio from it); options are keyword-only.
    """
    B = TCO.shape[0]
    _check("TCO", TCO, (B, 4, 4))
    _check("K", K, (B, 3, 3))
    _check("points", points, (B, None, 3))
    h, w = crop_resolution
    r = w / h
    uv = project_points(TCO, K, points, z_min)
    centre = project_points(TCO, K, torch.zeros_like(points[:, :1]), z_min)[:, 0]  # [B,2]
    dist = (uv - centre[:, None]).abs().amax(dim=1)  # [B,2]
    if extra_boxes is not None:
        _check("extra_boxes", extra_boxes, (B, 4))
        corners = extra_boxes.view(B, 2, 2).to(uv.dtype)  # (x1,y1), (x2,y2)
        dist = torch.maximum(dist, (corners - centre[:, None]).abs().amax(dim=1))
    half_w = torch.maximum(dist[:, 0], dist[:, 1] * r) * margin
    half_h = half_w / r
    half = torch.stack([half_w, half_h], dim=-1)
    return torch.cat([centre - half, centre + half], dim=-1)


def crop_intrinsics(K: Tensor, boxes: Tensor, crop_resolution: Size = CROP_RESOLUTION) -> Tensor:
    """``K_crop [B,3,3]`` of crops ``boxes [B,4]`` resized to ``crop_resolution`` (h, w).

    Crop pixel ``j`` samples the image at ``u = x1 + (j + 0.5) s`` (roi_align, aligned=True) and
    lies at ``u' = j + 0.5`` in the crop: ``u' = (u - x1) / s``, ``K_crop = A @ K`` (skew kept).
    """
    B = K.shape[0]
    _check("K", K, (B, 3, 3))
    _check("boxes", boxes, (B, 4))
    h, w = crop_resolution
    boxes = boxes.to(K.dtype)
    sx = (boxes[:, 2] - boxes[:, 0]) / w
    sy = (boxes[:, 3] - boxes[:, 1]) / h
    A = torch.zeros_like(K)
    A[:, 0, 0] = 1.0 / sx
    A[:, 1, 1] = 1.0 / sy
    A[:, 0, 2] = -boxes[:, 0] / sx
    A[:, 1, 2] = -boxes[:, 1] / sy
    A[:, 2, 2] = 1.0
    return A @ K


def _sample_grid(boxes: Tensor, crop_resolution: Size) -> tuple[Tensor, Tensor]:
    """Image coordinates sampled by each crop pixel: ``u [B,w]``, ``v [B,h]``."""
    h, w = crop_resolution
    j = torch.arange(w, dtype=boxes.dtype, device=boxes.device) + 0.5
    i = torch.arange(h, dtype=boxes.dtype, device=boxes.device) + 0.5
    sx = (boxes[:, 2:3] - boxes[:, 0:1]) / w
    sy = (boxes[:, 3:4] - boxes[:, 1:2]) / h
    return boxes[:, 0:1] + j * sx, boxes[:, 1:2] + i * sy


@lru_cache(maxsize=None)
def _crop_threads(n: int) -> ThreadPoolExecutor:
    """``n`` threads that crop in parallel (made on first use, kept for the process)."""
    return ThreadPoolExecutor(n, thread_name_prefix="cosy-lite-crops")


def _crop_bilinear(images: Tensor, boxes: Tensor, crop_resolution: Size, sampling_ratio: int) -> Tensor:
    if not images.is_floating_point():
        raise ValueError(f"bilinear crops need floating images, got {images.dtype} (use mode='nearest' for masks)")
    idx = torch.arange(len(boxes), dtype=images.dtype, device=images.device)[:, None]
    rois = torch.cat([idx, boxes.to(images.dtype)], dim=1)

    def crop(r: Tensor) -> Tensor:
        return roi_align(images, r, output_size=crop_resolution, spatial_scale=1.0, sampling_ratio=sampling_ratio,
                         aligned=True)

    # torchvision's CPU roi_align runs on one thread: outside autograd, the crops are split over torch's
    # threads (the op releases the GIL; each crop is computed alone, so the result is the same)
    n = min(torch.get_num_threads(), len(rois))
    if n < 2 or torch.is_grad_enabled() or images.device.type != "cpu":
        return crop(rois)
    parts = list(_crop_threads(n).map(_no_grad(crop), torch.tensor_split(rois, n)))
    return torch.cat(parts)


def _no_grad(f: Callable[[Tensor], Tensor]) -> Callable[[Tensor], Tensor]:
    """``f`` under ``torch.no_grad`` in whichever thread runs it (grad mode is per thread)."""
    def run(x: Tensor) -> Tensor:
        with torch.no_grad():
            return f(x)
    return run


def _crop_nearest(images: Tensor, boxes: Tensor, crop_resolution: Size, sampling_ratio: int) -> Tensor:
    B, C, H, W = images.shape
    u, v = _sample_grid(boxes.to(torch.float64), crop_resolution)
    iu, iv = torch.floor(u).long(), torch.floor(v).long()  # the pixel [i, i+1) holding the sample
    valid = ((iu >= 0) & (iu < W))[:, None, :] & ((iv >= 0) & (iv < H))[:, :, None]  # [B,h,w]
    b = torch.arange(B, device=images.device)[:, None, None]
    out = images.permute(0, 2, 3, 1)[b, iv.clamp(0, H - 1)[:, :, None], iu.clamp(0, W - 1)[:, None, :]]  # [B,h,w,C]
    out = torch.where(valid[..., None], out, torch.zeros((), dtype=images.dtype, device=images.device))
    return out.permute(0, 3, 1, 2).contiguous()


CROP_MODES: dict[str, Callable[[Tensor, Tensor, Size, int], Tensor]] = {
    "bilinear": _crop_bilinear,  # roi_align (aligned=True), averaging sampling_ratio^2 samples per pixel
    "nearest": _crop_nearest,  # the pixel nearest each sample point: masks, labels, depth
}


def crop_images(
    images: Tensor,
    boxes: Tensor,
    crop_resolution: Size = CROP_RESOLUTION,
    mode: str = "bilinear",
    sampling_ratio: int = SAMPLING_RATIO,
) -> Tensor:
    """Crop ``images [B,C,H,W]`` to ``boxes [B,4]`` (image coordinates), resized to ``crop_resolution``.

    ``mode``: a key of :data:`CROP_MODES`; ``"bilinear"`` needs floating images, ``"nearest"``
    takes any dtype (bool masks, ids, depth). Outside the image the crop is 0.
    Returns ``[B,C,h,w]``.
    """
    if mode not in CROP_MODES:
        raise ValueError(f"mode must be one of {sorted(CROP_MODES)}, got {mode!r}")
    _check("images", images, (None, None, None, None))
    _check("boxes", boxes, (images.shape[0], 4))
    return CROP_MODES[mode](images, boxes, cast(Size, tuple(crop_resolution)), sampling_ratio)

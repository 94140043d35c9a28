"""Pose-aware crops and ``K_crop`` in numpy: the onnxruntime path's twin of :mod:`.crops` (no torch).

Same rules and pixel convention as :mod:`cosy_lite.geometry.crops` (read its docstring): pixel ``i``
covers ``[i, i+1)``; the crop box is centred on the projected object origin, 4:3 (the crop's aspect
ratio), half-extent ``max(dx, r dy) * MARGIN``; ``K_crop`` maps the image to the crop's pixels.

:func:`crop_image` computes exactly what ``torchvision.ops.roi_align(aligned=True, spatial_scale=1,
sampling_ratio=SAMPLING_RATIO)`` computes, without torch: output pixel ``(i, j)`` is the mean of
``s x s`` bilinear samples at ``(y, x)`` sample positions that depend on ``i`` only (``y``) and on
``j`` only (``x``), and roi_align's bilinear weights and edge rules (zero beyond one pixel outside
the image, clamped to the border pixel within it) are products of a ``y`` factor and an ``x``
factor. So the crop is ``Wy @ image @ Wx^T`` with sparse ``Wy [h,H]``, ``Wx [w,W]`` holding at most
``2 s`` non-zeros per row; it is evaluated as gathers of those rows and columns (per crop: about
``2 s (h W' + h w) C`` multiply-adds, ``W'`` the image columns the box touches).

The constants equal :mod:`.crops`' (``tests/test_numpy_geometry.py`` checks); this module imports
numpy only, so the onnxruntime inference loop runs where torch is not installed.
"""

from __future__ import annotations

import numpy as np

Size = tuple[int, int]  # (height, width) in pixels

CROP_RESOLUTION: Size = (240, 320)  # as crops.CROP_RESOLUTION
MARGIN = 1.4  # as crops.MARGIN (CosyPose's lambda)
Z_MIN = 0.1  # m, as crops.Z_MIN
SAMPLING_RATIO = 2  # as crops.SAMPLING_RATIO: samples per output pixel and axis


def _check(name: str, x: np.ndarray, shape: tuple) -> None:
    """Raise ValueError unless ``x`` is an array of ``shape`` (``None`` = any size)."""
    ok = isinstance(x, np.ndarray) and x.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, x.shape))
    if not ok:
        want = "[" + ",".join("*" if s is None else str(s) for s in shape) + "]"
        got = x.shape if isinstance(x, np.ndarray) else type(x).__name__
        raise ValueError(f"{name} must be a numpy array of shape {want}, got {got}")


def project_points(TCO: np.ndarray, K: np.ndarray, points: np.ndarray, z_min: float = Z_MIN) -> np.ndarray:
    """``[B,N,2]`` image coordinates ``(u, v)`` of object points ``[B,N,3]`` (m) at poses ``TCO [B,4,4]``
    seen by ``K [B,3,3]``; depths clamped to ``>= z_min`` (finite coordinates behind the camera)."""
    p = points @ np.swapaxes(TCO[:, :3, :3], 1, 2) + TCO[:, None, :3, 3]
    p = p @ np.swapaxes(K, 1, 2)
    return p[..., :2] / np.maximum(p[..., 2:3], z_min)


def crop_boxes(TCO: np.ndarray, K: np.ndarray, points: np.ndarray, *, crop_resolution: Size = CROP_RESOLUTION,
               margin: float = MARGIN, z_min: float = Z_MIN) -> np.ndarray:
    """Crop boxes ``[B,4]`` (x1, y1, x2, y2; image coordinates) of objects at ``TCO [B,4,4]`` (m).

    ``K [B,3,3]``; ``points [B,N,3]`` (m) model points. As :func:`cosy_lite.geometry.crops.crop_boxes`
    (without ``extra_boxes``): centred on the projected origin, half-width ``max(dx, r dy) * margin``,
    half-height = half-width / r, ``r = w / h`` of ``crop_resolution`` (h, w). In the arrays' dtype.
    """
    B = TCO.shape[0] if isinstance(TCO, np.ndarray) and TCO.ndim == 3 else -1
    _check("TCO", TCO, (B, 4, 4))
    _check("K", K, (B, 3, 3))
    _check("points", points, (B, None, 3))
    h, w = crop_resolution
    r = w / h
    uv = project_points(TCO, K, points, z_min)
    centre = project_points(TCO, K, np.zeros_like(points[:, :1]), z_min)[:, 0]  # [B,2]
    dist = np.abs(uv - centre[:, None]).max(axis=1)  # [B,2]
    half_w = np.maximum(dist[:, 0], dist[:, 1] * r) * margin
    half = np.stack([half_w, half_w / r], axis=-1)
    return np.concatenate([centre - half, centre + half], axis=-1)


def crop_intrinsics(K: np.ndarray, boxes: np.ndarray, crop_resolution: Size = CROP_RESOLUTION) -> np.ndarray:
    """``K_crop [B,3,3]`` of crops ``boxes [B,4]`` resized to ``crop_resolution`` (h, w):
    ``u' = (u - x1) / s``, ``s = (x2 - x1) / w`` (likewise v), ``K_crop = A @ K`` (skew kept)."""
    B = K.shape[0] if isinstance(K, np.ndarray) and K.ndim == 3 else -1
    _check("K", K, (B, 3, 3))
    _check("boxes", boxes, (B, 4))
    h, w = crop_resolution
    boxes = boxes.astype(K.dtype, copy=False)
    sx = (boxes[:, 2] - boxes[:, 0]) / w
    sy = (boxes[:, 3] - boxes[:, 1]) / h
    A = np.zeros_like(K)
    A[:, 0, 0] = 1.0 / sx
    A[:, 1, 1] = 1.0 / sy
    A[:, 0, 2] = -boxes[:, 0] / sx
    A[:, 1, 2] = -boxes[:, 1] / sy
    A[:, 2, 2] = 1.0
    return A @ K


def axis_weights(start: float, end: float, n_out: int, n_in: int,
                 sampling_ratio: int = SAMPLING_RATIO) -> tuple[np.ndarray, np.ndarray]:
    """roi_align's sampling along one axis, as (indices ``[n_out, 2 s]`` int64, weights ``[n_out, 2 s]``).

    The box ``[start, end)`` (image coordinates) is cut into ``n_out`` bins of ``s = sampling_ratio``
    samples each; sample ``k`` of bin ``j`` lies at ``p = start - 0.5 + (j + (k + 0.5) / s) (end -
    start) / n_out`` in pixel-centre units. Beyond one pixel outside ``[0, n_in - 1]`` it weighs 0;
    otherwise it is clamped into the image and split between its two neighbouring pixels. Each
    weight carries the ``1 / s`` of the bin's mean, so ``crop = sum_k w[:, k] * line[idx[:, k]]``.
    """
    s = int(sampling_ratio)
    if s < 1:
        raise ValueError(f"sampling_ratio must be >= 1, got {sampling_ratio}")
    bin_size = (end - start) / n_out
    offsets = (np.arange(s, dtype=np.float64) + 0.5) / s
    p = (start - 0.5) + (np.arange(n_out, dtype=np.float64)[:, None] + offsets) * bin_size  # [n_out, s]
    inside = (p >= -1.0) & (p <= n_in)
    p = np.maximum(p, 0.0)
    low = np.floor(p).astype(np.int64)
    at_end = low >= n_in - 1
    low = np.where(at_end, n_in - 1, low)
    high = np.where(at_end, n_in - 1, low + 1)
    frac = np.where(at_end, 0.0, p - low)
    scale = inside / s
    idx = np.concatenate([low, high], axis=1)
    weights = np.concatenate([(1.0 - frac) * scale, frac * scale], axis=1)
    return idx, weights


def crop_image(image: np.ndarray, boxes: np.ndarray, crop_resolution: Size = CROP_RESOLUTION,
               sampling_ratio: int = SAMPLING_RATIO, out: np.ndarray | None = None) -> np.ndarray:
    """Crops of one ``image [H,W,C]`` (float) to ``boxes [B,4]`` (image coordinates), resized to
    ``crop_resolution`` (h, w): ``[B,C,h,w]`` in the image's dtype, 0 outside the image.

    Equals :func:`cosy_lite.geometry.crops.crop_images` (``mode="bilinear"``: ``roi_align``,
    ``aligned=True``) of the image repeated B times, to float rounding. ``out``: an array
    ``[B,C,h,w]`` (or a view such as ``inputs[:, :3]``) to write into instead of a new one.
    """
    _check("image", image, (None, None, None))
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"image must be floating (e.g. rgb / 255 as float32), got {image.dtype}")
    B = boxes.shape[0] if isinstance(boxes, np.ndarray) and boxes.ndim == 2 else -1
    _check("boxes", boxes, (B, 4))
    H, W, C = image.shape
    h, w = (int(v) for v in crop_resolution)
    if out is None:
        out = np.empty((B, C, h, w), dtype=image.dtype)
    elif out.shape != (B, C, h, w):
        raise ValueError(f"out must be [{B},{C},{h},{w}], got {out.shape}")
    for b, (x1, y1, x2, y2) in enumerate(np.asarray(boxes, dtype=np.float64).tolist()):
        iy, wy = axis_weights(y1, y2, h, H, sampling_ratio)
        ix, wx = axis_weights(x1, x2, w, W, sampling_ratio)
        wy, wx = wy.astype(image.dtype), wx.astype(image.dtype)
        c0, c1 = int(ix.min()), int(ix.max()) + 1  # the rows pass reads only the columns the crop uses
        rows = np.einsum("hk,hkwc->hwc", wy, image[iy, c0:c1])  # [h, c1-c0, C]
        crop = np.einsum("wk,hwkc->chw", wx, rows[:, ix - c0])  # [C, h, w]
        out[b] = crop
    return out

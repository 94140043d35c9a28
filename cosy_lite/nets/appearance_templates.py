"""Start poses that look at the texture: silhouette templates ranked by appearance as well.

A silhouette cannot tell a box from its flipped twin; the print on it can. Each silhouette template
(:class:`~cosy_lite.nets.silhouette_templates.SilhouetteTemplates`: the same rotations, the same
on-axis template camera) is also rendered textured, shaded as the refiner renders, cut to the same
square around its box as the occupancy grids, and described by a frozen ImageNet EfficientNet-Lite0
(:class:`AppearanceDescriptor`: its stride-8 and stride-16 feature maps, unit length per cell). A
detection is seen the same way: the image turned with the mask towards the camera axis, cut to the
square around the mask's box, background black. Each template then scores

    mean cosine similarity of the cells (stride 8) + mean cosine similarity (stride 16)
    + ``iou_weight`` x silhouette soft IoU

and the best scores start the refiner. No training: the trunk is the ImageNet one, and the
descriptors of an object's 2,048 templates are computed once (~20 s per object on one core: rendering ~10 s, trunk ~9 s) and
cached as ``.npz`` beside the silhouettes (keyed by the mesh hash and the settings).

Measured on 96 test instances of ycbvsynth (visible fraction >= 0.5, GT masks; bench/RESULTS.md,
"Appearance start"): the best-scored template is within 30 deg of GT for 49-51 % of them, against
24 % for the silhouettes alone and 40 % for today's silhouettes top 5 + refiner confidence, at
0.05 s per instance.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence, TypeAlias

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cosy_lite.nets.batchnorm_folding import batchnorm_folded
from cosy_lite.nets.silhouette_templates import BOX_MARGIN, TEMPLATE_SIZE, MaskView, SilhouetteTemplates, file_key, mask_boxes

if TYPE_CHECKING:
    from cosy_lite.render.renderer import MeshRenderer, Renderer

CROP_SIZE = 64  # px: the square each template and detection is described at
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
RENDER_BATCH = 256

# describes the detections for a trained scorer: crops [B,3,S,S] in [0, 1] -> descriptors [B,D], with an
# iou_weight (the silhouette's share of the score); an AppearanceScorer or its onnxruntime session (OnnxScorer)
Scorer: TypeAlias = Callable[[Tensor], Tensor]


def square_crops(images: np.ndarray, masks: np.ndarray, boxes: np.ndarray, size: int = CROP_SIZE) -> Tensor:
    """``[B,3,size,size]`` float32 in [0, 1]: each image (``[B,H,W,3]`` uint8) with its ``masks``
    ``[B,H,W]`` (bool; outside black) cut to the square of side ``BOX_MARGIN x`` its box's longer
    side around the box (the occupancy grids' square, :func:`silhouette_templates.occupancy_grids`)."""
    out = np.zeros((len(images), size, size, 3), np.float32)
    for i, (im, m, b) in enumerate(zip(images, masks, boxes)):
        if not np.isfinite(b).all():
            continue
        cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
        half = max(b[2] - b[0], b[3] - b[1]) / 2 * BOX_MARGIN + 1.0
        a = 2 * half / size  # source pixels per crop pixel
        M = np.array([[a, 0.0, cx - half + 0.5 * a - 0.5], [0.0, a, cy - half + 0.5 * a - 0.5]])
        x = im.astype(np.float32) * (m[..., None] / np.float32(255.0))
        out[i] = cv2.warpAffine(x, M, (size, size), flags=cv2.INTER_AREA | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return torch.from_numpy(out).permute(0, 3, 1, 2)


class AppearanceDescriptor(nn.Module):
    """Frozen ImageNet EfficientNet-Lite0 up to stride 16: ``[B,3,S,S]`` in [0, 1] -> ``[B,D]``
    float32, the stride-8 and stride-16 feature maps, each cell scaled to unit length and divided by
    the square root of its map's cell count (so a dot product is the sum of two mean cosines)."""

    # buffers (register_buffer), declared for type checkers
    mean: Tensor  # [3, 1, 1] ImageNet mean
    std: Tensor  # [3, 1, 1]

    def __init__(self, trunk: str = "efficientnet_lite0", load_weights: bool = True):
        super().__init__()
        from cosy_lite.nets.pretrained import lite_features

        # channels_last: 2.3x faster on this CPU (2,048 template crops of 64x64: 21 -> 9 s per object)
        self.trunk = lite_features(trunk, (2, 3), pretrained=load_weights).eval().to(memory_format=torch.channels_last)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN)[:, None, None])
        self.register_buffer("std", torch.tensor(IMAGENET_STD)[:, None, None])

    def forward(self, images: Tensor) -> Tensor:
        maps = self.trunk(((images - self.mean) / self.std).contiguous(memory_format=torch.channels_last))
        parts = [F.normalize(f, dim=1).flatten(1) / float(f.shape[-2] * f.shape[-1]) ** 0.5 for f in maps]
        return torch.cat(parts, dim=1)


class AppearanceTemplates:
    """Appearance descriptors of the templates of ``silhouettes``, and the scores of a detection.

    Args:
        silhouettes: the templates (rotations, depths, boxes, IoU); this scorer attaches itself as
            their ``appearance`` so that their ``match`` ranks by appearance when given the image.
        renderer: a renderer of the objects with the refiner's shading (``headlight``).
        descriptor: an :class:`AppearanceDescriptor` (default: built, ImageNet weights read once).
        iou_weight: weight of the silhouette soft IoU in the score (with a ``scorer``: its own).
        cache_dir, model_keys: as :class:`SilhouetteTemplates` (descriptors kept as float16 ``.npz``).
        scorer: a trained :class:`~cosy_lite.nets.appearance_scorer.AppearanceScorer` (or its
            onnxruntime session, :class:`~cosy_lite.inference.onnx_runtime.OnnxScorer`: crops in,
            descriptors out, with an ``iou_weight``) that describes the detections (the templates
            keep the frozen ``descriptor``); None: the frozen descriptor on both sides.
    """

    def __init__(self, silhouettes: SilhouetteTemplates, renderer: Renderer, descriptor: AppearanceDescriptor | None = None,
                 iou_weight: float = 0.5, cache_dir: str | Path | None = None, model_keys: dict[int, str] | None = None,
                 scorer: Scorer | None = None):
        self.silhouettes = silhouettes
        self.renderer = renderer
        # built here, the frozen descriptor runs BatchNorm folded: the same descriptors, the templates described faster
        self.descriptor = descriptor or batchnorm_folded(AppearanceDescriptor(), (2, 3, CROP_SIZE, CROP_SIZE))
        if isinstance(scorer, nn.Module):
            scorer.eval()
        self.scorer = scorer
        # the scorer's own: an AppearanceScorer's nn.Parameter, an OnnxScorer's float
        self.iou_weight = (float(iou_weight) if scorer is None
                           else float(torch.as_tensor(getattr(scorer, "iou_weight")).detach()))  # noqa: B009 (a Callable)
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.model_keys = {int(k): str(v) for k, v in (model_keys or {}).items()}
        self._cache: dict[int, Tensor] = {}
        silhouettes.appearance = self

    def ready(self, obj_id: int) -> bool:
        """Whether the descriptors of ``obj_id`` are in memory."""
        return int(obj_id) in self._cache

    def descriptors(self, obj_id: int) -> Tensor:
        """``[N,D]`` float32 descriptors of the templates of ``obj_id`` (computed on first use)."""
        obj_id = int(obj_id)
        if obj_id not in self._cache:
            path = self._cache_path(obj_id)
            cached = _read_descriptors(path, self.silhouettes.n_rotations) if path is not None else None
            # float16 as in the cache file, so a first run and a cached one score alike
            self._cache[obj_id] = cached if cached is not None else self._describe_templates(obj_id).half().float()
            if path is not None and cached is None:
                _write_descriptors(path, self._cache[obj_id])
        return self._cache[obj_id]

    def _cache_path(self, obj_id: int) -> Path | None:
        if self.cache_dir is None or obj_id not in self.model_keys:
            return None
        s = self.silhouettes
        settings = (f"appearance|{self.model_keys[obj_id]}|{s.diameters[obj_id]:.6f}|{s.n_rotations}|{s.seed}|"
                    f"{TEMPLATE_SIZE}|{BOX_MARGIN}|{CROP_SIZE}|{getattr(self.renderer, 'shading', '')}")
        return self.cache_dir / f"appearance_obj{obj_id:06d}_{hashlib.sha256(settings.encode()).hexdigest()[:20]}.npz"

    def _describe_templates(self, obj_id: int) -> Tensor:
        t = self.silhouettes.templates(obj_id)
        TCO = np.tile(np.eye(4), (len(t.rotations), 1, 1))
        TCO[:, :3, :3] = t.rotations
        TCO[:, 2, 3] = t.depth
        out = []
        for s in range(0, len(TCO), RENDER_BATCH):
            T = TCO[s:s + RENDER_BATCH]
            r = self.renderer.render([obj_id] * len(T), T, self.silhouettes.template_K, (TEMPLATE_SIZE, TEMPLATE_SIZE))
            assert r.rgb is not None  # (rendered with colour)
            with torch.no_grad():
                out.append(self.descriptor(square_crops(r.rgb, r.mask, mask_boxes(r.mask))))
        return torch.cat(out)

    def describe(self, rgb: np.ndarray, view: MaskView, K: np.ndarray) -> Tensor:
        """``[D]``: the detection of ``view`` in the image ``rgb [H,W,3]`` uint8, seen as the templates
        are (by the trained scorer when there is one)."""
        with torch.no_grad():
            return (self.descriptor if self.scorer is None else self.scorer)(detection_crop(rgb, view, K)[None])[0]

    def score(self, obj_id: int, rgb: np.ndarray, view: MaskView, K: np.ndarray, iou: np.ndarray) -> np.ndarray:
        """``[N]`` scores of the templates of ``obj_id`` for the detection of ``view`` (``iou``: their
        silhouette soft IoU)."""
        similarity = self.descriptors(obj_id) @ self.describe(rgb, view, K)
        return similarity.double().numpy() + self.iou_weight * np.asarray(iou, dtype=np.float64)


def object_templates(renderer: MeshRenderer, obj_ids: Sequence[int], diameters: Sequence[float], models_dir: str | Path,
                     cache_dir: str | Path | None, appearance: bool = True, scorer: Scorer | None = None,
                     n_rotations: int = 2048) -> SilhouetteTemplates:
    """The silhouette templates of ``obj_ids`` (``diameters`` in m), with their appearance scorer
    attached when ``appearance`` (the trained ``scorer`` describing detections when given); with a
    ``cache_dir``, kept there keyed by the sha256 of each ``models_dir/obj_XXXXXX.ply``."""
    keys = {} if cache_dir is None else {int(i): file_key(Path(models_dir) / f"obj_{int(i):06d}.ply") for i in obj_ids}
    templates = SilhouetteTemplates(renderer, obj_ids, diameters, n_rotations, cache_dir=cache_dir, model_keys=keys)
    if appearance:
        AppearanceTemplates(templates, renderer, cache_dir=cache_dir, model_keys=keys, scorer=scorer)  # attaches itself
    return templates


def textured_obj_ids(renderer: MeshRenderer, obj_ids: Sequence[int]) -> list[int]:
    """The objects whose mesh carries a texture image (their print can tell a flipped pose)."""
    return [o for o in obj_ids if getattr(renderer.mesh(o).visual, "kind", None) == "texture"]


def detection_crop(rgb: np.ndarray, view: MaskView, K: np.ndarray) -> Tensor:
    """``[3,S,S]`` float32 in [0, 1]: the image ``rgb [H,W,3]`` uint8 turned as the mask of ``view``
    (:meth:`SilhouetteTemplates.observe`), cut to the square around its box, outside the mask black."""
    H = K @ view.R.T @ np.linalg.inv(K)  # real image -> the turned camera's image (as the mask)
    h, w = view.mask.shape
    turned = cv2.warpPerspective(np.ascontiguousarray(rgb), H, (w, h), flags=cv2.INTER_LINEAR)
    return square_crops(turned[None], view.mask[None], view.box[None])[0]


def _write_descriptors(path: Path, d: Tensor) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
    np.savez_compressed(tmp, descriptors=d.numpy().astype(np.float16))
    os.replace(tmp, path)


def _read_descriptors(path: Path, n: int) -> Tensor | None:
    """The descriptors of ``path`` (None when absent; a damaged file is reported and computed again)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            d = f["descriptors"]
        if d.ndim != 2 or len(d) != n or not np.isfinite(d).all():
            raise ValueError(f"expected {n} finite descriptors, got an array of shape {d.shape}")
        return torch.from_numpy(d.astype(np.float32))
    except Exception as e:  # noqa: BLE001 - any damage: compute again
        warnings.warn(f"{path}: appearance cache unreadable ({e}); describing the templates again", RuntimeWarning,
                      stacklevel=3)
        return None

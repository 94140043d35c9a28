"""Training-free coarse poses: the detection mask matched against rendered silhouette templates.

Per object, ``n_rotations`` random rotations are rendered (depth only) with the object's origin on
the optical axis of a template camera; each silhouette becomes an ``S x S`` occupancy grid over the
square around its box (:func:`occupancy_grids`). A detection's mask is normalised the same way over
its own box; the templates with the highest soft IoU give the rotation *relative to the viewing
ray* (allocentric), the box sizes give the depth (template depth x template box / observed box, in
focal units) and the box centres give where the origin projects. The camera-frame rotation is then
``R_ray(t) @ R_allo`` (:func:`ray_rotations`: the ray's rotation of the template's optical axis).

Measured on 128 held-out ycbv-synth instances with visible GT masks (bench/RESULTS.md, issue 13):
the best template then 4 refiner iterations gives MSSD recall 0.078 where the box-canonical start
(with or without the trained coarse network) gives 0.008; the best of the top 20 templates is within
30 deg of GT for 57 % of the instances. numpy + OpenCV only (the onnxruntime path imports no torch).
"""

from __future__ import annotations

import hashlib
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import cv2
import numpy as np

from cosy_lite.geometry.depth import mask_box

if TYPE_CHECKING:
    from cosy_lite.render.renderer import Renderer

TEMPLATE_FOCAL = 300.0  # px, of the template camera
TEMPLATE_SIZE = 128  # px, square template images
TEMPLATE_FILL = 0.6  # the object's diameter spans this fraction of a template image
BOX_MARGIN = 1.05  # the occupancy square is this much larger than the box's longer side
RENDER_BATCH = 256


def random_rotations(n: int, seed: int = 0) -> np.ndarray:
    """``[n,3,3]`` float64 rotations uniform on SO(3) (normalised Gaussian quaternions)."""
    q = np.random.default_rng(seed).standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1).reshape(n, 3, 3)


def ray_rotations(t: np.ndarray) -> np.ndarray:
    """``[B,3,3]``: the smallest rotation taking the camera's z axis onto the ray through ``t [B,3]``."""
    t = np.asarray(t, dtype=np.float64)
    d = t / np.linalg.norm(t, axis=1, keepdims=True)
    v = np.cross(np.array([0.0, 0.0, 1.0]), d)
    c = d[:, 2]
    vx = np.zeros((len(t), 3, 3))
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 0] = -v[:, 2], v[:, 1], v[:, 2]
    vx[:, 1, 2], vx[:, 2, 0], vx[:, 2, 1] = -v[:, 0], -v[:, 1], v[:, 0]
    return np.eye(3) + vx + vx @ vx / (1.0 + c)[:, None, None]


def mask_boxes(masks: np.ndarray) -> np.ndarray:
    """``[B,4]`` float64 boxes x1, y1, x2, y2 (pixel edges: x2 = last column + 1) of ``masks [B,H,W]``;
    NaN for an empty mask."""
    out = np.full((len(masks), 4), np.nan)
    for i, m in enumerate(masks):
        if (box := mask_box(m)) is not None:
            out[i] = box
    return out


def occupancy_grids(masks: np.ndarray, boxes: np.ndarray, size: int) -> np.ndarray:
    """``[B,size,size]`` uint8 (0-255): each mask's occupancy over the square of side
    ``BOX_MARGIN x`` its box's longer side, centred on the box (bilinear at twice the resolution,
    then 2x2 averages)."""
    out = np.zeros((len(masks), size, size), dtype=np.uint8)
    n = 2 * size
    for i, (m, b) in enumerate(zip(masks, boxes)):
        if not np.isfinite(b).all():
            continue
        cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
        half = max(b[2] - b[0], b[3] - b[1]) / 2 * BOX_MARGIN + 1.0
        a = 2 * half / n  # source pixels per grid pixel; pixel centres at index + 0.5 in edge units
        M = np.array([[a, 0.0, cx - half + 0.5 * a - 0.5], [0.0, a, cy - half + 0.5 * a - 0.5]])
        fine = cv2.warpAffine(m.astype(np.float32), M, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        out[i] = np.round(fine.reshape(size, 2, size, 2).mean(axis=(1, 3)) * 255).astype(np.uint8)
    return out


@dataclass
class ObjectTemplates:
    """One object's templates: rotations [N,3,3] (allocentric), grids [N,S,S] uint8, boxes [N,4]
    (template px, edges), depth (m) the templates were rendered at."""

    rotations: np.ndarray
    grids: np.ndarray
    boxes: np.ndarray
    depth: float

    def __post_init__(self) -> None:
        self.areas = self.grids.sum(axis=(1, 2), dtype=np.int64)  # soft IoU: union = areas + observed - inter


@dataclass
class MaskView:
    """A detection mask seen by a camera turned by ``R`` [3,3] to look at it: the ``mask`` [H,W] bool
    it sees, its ``box`` [4] and its occupancy ``grid`` [S,S] uint8 (:func:`occupancy_grids`)."""

    R: np.ndarray
    mask: np.ndarray
    box: np.ndarray
    grid: np.ndarray


@dataclass
class TemplateMatches:
    """The ``k`` best templates of each of B detections: TCO [B,k,4,4] float64 (m), scores [B,k]
    (soft IoU in [0, 1], decreasing), found [B] bool (False: empty mask, TCO is NaN)."""

    TCO: np.ndarray
    scores: np.ndarray
    found: np.ndarray


class SilhouetteTemplates:
    """Silhouette templates of some objects, and the matching of detection masks against them.

    Args:
        renderer: a :class:`~cosy_lite.render.renderer.Renderer` of the objects (depth only is used).
        obj_ids, diameters: the objects and their diameters (m; they set the template depth).
        n_rotations: templates per object; grid: side S of the occupancy grids; seed: of the rotations;
        rotations: ``[N,3,3]`` rotations to use instead of ``n_rotations`` random ones.
        cache_dir, model_keys: with both, an object's templates are kept in ``cache_dir`` as a
            ``.npz`` (no pickle) named by its ``model_keys[obj_id]`` (e.g. a hash of its mesh file,
            :func:`file_key`) and the settings, and read back instead of rendered.
    Templates are rendered on first use of each object (~4 s per object for 2,048 on one core).
    """

    def __init__(self, renderer: Renderer, obj_ids: Sequence[int], diameters: Sequence[float],
                 n_rotations: int = 2048, grid: int = 32, seed: int = 0, rotations: np.ndarray | None = None,
                 cache_dir: str | Path | None = None, model_keys: Mapping[int, str] | None = None):
        if rotations is not None:
            rotations = np.asarray(rotations, dtype=np.float64)
            if rotations.ndim != 3 or rotations.shape[1:] != (3, 3) or not np.isfinite(rotations).all():
                raise ValueError(f"rotations must be a finite [N,3,3], got {rotations.shape}")
            n_rotations = len(rotations)
        if n_rotations < 1 or grid < 4:
            raise ValueError(f"n_rotations must be >= 1 and grid >= 4, got {n_rotations}, {grid}")
        if len(obj_ids) != len(diameters):
            raise ValueError(f"{len(obj_ids)} obj_ids but {len(diameters)} diameters")
        self.renderer = renderer
        self.diameters = {int(o): float(d) for o, d in zip(obj_ids, diameters)}
        self.n_rotations, self.grid = int(n_rotations), int(grid)
        self.rotations = random_rotations(self.n_rotations, seed) if rotations is None else rotations
        self.seed = int(seed)
        # explicit rotations are not what the file name says: not cached
        self.cache_dir = None if cache_dir is None or rotations is not None else Path(cache_dir)
        self.model_keys = {int(k): str(v) for k, v in (model_keys or {}).items()}
        self._cache: dict[int, ObjectTemplates] = {}
        self.appearance: Any = None  # an AppearanceTemplates ranking by appearance too (see match)

    @property
    def template_K(self) -> np.ndarray:
        c = TEMPLATE_SIZE / 2
        return np.array([[TEMPLATE_FOCAL, 0.0, c], [0.0, TEMPLATE_FOCAL, c], [0.0, 0.0, 1.0]])

    def templates(self, obj_id: int) -> ObjectTemplates:
        """The templates of ``obj_id`` (rendered on first call)."""
        obj_id = int(obj_id)
        if obj_id not in self._cache:
            if obj_id not in self.diameters:
                raise KeyError(f"no templates of obj_id {obj_id} (objects: {sorted(self.diameters)})")
            path = self._cache_path(obj_id)
            cached = _read_templates(path, self.n_rotations, self.grid) if path is not None else None
            self._cache[obj_id] = cached or self._render(obj_id)
            if path is not None and cached is None:
                _write_templates(path, self._cache[obj_id])
        return self._cache[obj_id]

    def ready(self, obj_id: int) -> bool:
        """Whether the templates of ``obj_id`` (and their appearance descriptors) are in memory."""
        return int(obj_id) in self._cache and (self.appearance is None or self.appearance.ready(obj_id))

    def prepare(self, obj_ids: Sequence[int], progress: bool = False) -> float:
        """Render (or read from the cache) the templates of those of ``obj_ids`` not ready yet, with their
        appearance descriptors: the one-time cost of a template start, kept apart from an image's time.
        ``progress``: a bar over the objects (on a terminal). Returns the seconds spent."""
        from tqdm import tqdm

        todo = [int(o) for o in dict.fromkeys(int(i) for i in obj_ids) if not self.ready(o)]
        if not todo:
            return 0.0
        t0 = time.perf_counter()
        for obj_id in tqdm(todo, desc="templates", unit="object", disable=None if progress else True, leave=False):
            self.templates(obj_id)
            if self.appearance is not None:
                self.appearance.descriptors(obj_id)
        return time.perf_counter() - t0

    def _cache_path(self, obj_id: int) -> Path | None:
        if self.cache_dir is None or obj_id not in self.model_keys:
            return None
        settings = f"{self.model_keys[obj_id]}|{self.diameters[obj_id]:.6f}|{self.n_rotations}|{self.grid}|{self.seed}|" \
                   f"{TEMPLATE_FOCAL}|{TEMPLATE_SIZE}|{TEMPLATE_FILL}|{BOX_MARGIN}"
        key = hashlib.sha256(settings.encode()).hexdigest()[:20]
        return self.cache_dir / f"templates_obj{obj_id:06d}_{key}.npz"

    def _render(self, obj_id: int) -> ObjectTemplates:
        """Render the templates of ``obj_id``."""
        depth = TEMPLATE_FOCAL * self.diameters[obj_id] / (TEMPLATE_FILL * TEMPLATE_SIZE)
        TCO = np.tile(np.eye(4), (self.n_rotations, 1, 1))
        TCO[:, :3, :3] = self.rotations
        TCO[:, 2, 3] = depth
        grids, boxes = [], []
        for s in range(0, self.n_rotations, RENDER_BATCH):
            T = TCO[s:s + RENDER_BATCH]
            masks = self.renderer.render([obj_id] * len(T), T, self.template_K, (TEMPLATE_SIZE, TEMPLATE_SIZE),
                                         depth_only=True).depth > 0
            b = mask_boxes(masks)
            grids.append(occupancy_grids(masks, b, self.grid))
            boxes.append(b)
        return ObjectTemplates(self.rotations, np.concatenate(grids), np.concatenate(boxes), depth)

    def match(self, masks: np.ndarray, obj_ids: Sequence[int], K: np.ndarray, top_k: int = 1,
              rgb: np.ndarray | None = None) -> TemplateMatches:
        """The ``top_k`` template poses of each detection: ``masks [B,H,W]`` bool (visible masks),
        ``obj_ids [B]``, ``K [B,3,3]`` or ``[3,3]`` intrinsics of the image (px). With an
        ``appearance`` scorer (:class:`~cosy_lite.nets.appearance_templates.AppearanceTemplates`)
        and the image ``rgb [H,W,3]`` uint8, templates are ranked by appearance + silhouette
        (its ``score``), else by silhouette soft IoU alone."""
        masks = np.asarray(masks, dtype=bool)
        B = len(masks)
        K = np.broadcast_to(np.asarray(K, dtype=np.float64), (B, 3, 3))
        k = min(int(top_k), self.n_rotations)
        TCO = np.full((B, k, 4, 4), np.nan)
        scores = np.zeros((B, k))
        boxes = mask_boxes(masks)
        found = np.isfinite(boxes).all(axis=1)
        for i in np.flatnonzero(found):
            view = self.observe(masks[i], boxes[i], K[i])
            if view is None:
                found[i] = False
                continue
            obj_id = int(obj_ids[int(i)])
            t = self.templates(obj_id)
            score = self.silhouette_iou(t, view.grid)
            if self.appearance is not None and rgb is not None:
                score = self.appearance.score(obj_id, rgb, view, K[i], score)
            best = np.argsort(-score, kind="stable")[:k]
            scores[i] = score[best]
            TCO[i] = self.poses(t, best, view, K[i])
        return TemplateMatches(TCO, scores, found)

    def observe(self, mask: np.ndarray, box: np.ndarray, K: np.ndarray) -> "MaskView | None":
        """The detection ``mask`` (its ``box``, :func:`mask_boxes`) as the templates see objects: by
        a camera turned to look at it (:meth:`_look_at_mask`), over its box's square; None when the
        turned camera sees none of it."""
        R_view, virtual = self._look_at_mask(mask, box, K)
        vbox = mask_boxes(virtual[None])[0]
        if not np.isfinite(vbox).all():
            return None
        return MaskView(R_view, virtual, vbox, occupancy_grids(virtual[None], vbox[None], self.grid)[0])

    @staticmethod
    def silhouette_iou(t: ObjectTemplates, observed: np.ndarray) -> np.ndarray:
        """``[N]`` soft IoU of each template's occupancy grid with the ``observed`` one."""
        inter = np.minimum(t.grids, observed).sum(axis=(1, 2), dtype=np.int64)
        union = t.areas + int(observed.sum(dtype=np.int64)) - inter  # min + max = a + b
        return inter / np.maximum(union, 1)

    def poses(self, t: ObjectTemplates, which: np.ndarray, view: "MaskView", K: np.ndarray) -> np.ndarray:
        """``[len(which),4,4]`` camera-frame poses of templates ``which`` placed on the ``view``."""
        T_view = np.eye(4)
        T_view[:3, :3] = view.R
        return T_view @ self._poses(t, which, view.box, K)

    @staticmethod
    def _look_at_mask(mask: np.ndarray, box: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R [3,3], mask [H,W] bool): the camera rotated by R to look through the centre of
        ``mask``'s ``box`` (:func:`mask_boxes`), and what it sees. Off the optical axis a silhouette is a perspective warp of
        the on-axis one (measured: the true template's soft IoU falls from 0.95 to 0.61-0.83 at
        10-16 deg off-axis); the rotated camera sees the object near its axis, as the templates do."""
        centre = np.array([(box[0] + box[2]) / 2 - 0.5, (box[1] + box[3]) / 2 - 0.5, 1.0])
        R = ray_rotations((np.linalg.inv(K) @ centre)[None])[0]
        H = K @ R.T @ np.linalg.inv(K)  # real image -> rotated camera's image
        h, w = mask.shape
        seen = cv2.warpPerspective(mask.astype(np.float32), H, (w, h), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        return R, seen > 0.5

    def _poses(self, t: ObjectTemplates, which: np.ndarray, box: np.ndarray, K: np.ndarray) -> np.ndarray:
        """``[len(which),4,4]``: templates ``which`` of ``t`` placed so that their box lands on ``box``."""
        tb = t.boxes[which]
        side_t = (tb[:, 2:] - tb[:, :2]).max(axis=1)
        side_o = float((box[2:] - box[:2]).max())
        f_o = float(np.sqrt(K[0, 0] * K[1, 1]))
        z = t.depth * (side_t / TEMPLATE_FOCAL) / (side_o / f_o)
        scale = side_o / side_t  # observed px per template px
        origin_t = TEMPLATE_SIZE / 2 + 0.5  # where the template origin projects, in pixel-edge units
        offset = ((tb[:, :2] + tb[:, 2:]) / 2 - origin_t) * scale[:, None]
        origin = (box[:2] + box[2:]) / 2 - offset - 0.5  # the origin's projection, pixel-centre units
        xy = (origin - K[:2, 2]) / np.array([K[0, 0], K[1, 1]]) * z[:, None]
        T = np.tile(np.eye(4), (len(which), 1, 1))
        T[:, :3, 3] = np.concatenate([xy, z[:, None]], axis=1)
        T[:, :3, :3] = ray_rotations(T[:, :3, 3]) @ t.rotations[which]
        return T


def file_key(path: str | Path) -> str:
    """sha256 of a file's bytes (a mesh file: its templates' cache key)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _write_templates(path: Path, t: ObjectTemplates) -> None:
    """Atomically (temporary file + rename), so that an interrupted run leaves no half file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
    np.savez_compressed(tmp, rotations=t.rotations, grids=t.grids, boxes=t.boxes, depth=np.float64(t.depth))
    os.replace(tmp, path)


def _read_templates(path: Path, n: int, grid: int) -> ObjectTemplates | None:
    """The templates of ``path`` (None when absent; a file that is unreadable or of other shapes is
    reported with a warning naming it and rendered again)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            t = ObjectTemplates(f["rotations"], f["grids"], f["boxes"], float(f["depth"]))
        if (t.rotations.shape != (n, 3, 3) or t.grids.shape != (n, grid, grid) or t.grids.dtype != np.uint8
                or t.boxes.shape != (n, 4) or not np.isfinite(t.depth)):
            raise ValueError(f"arrays of other shapes than {n} templates of {grid}x{grid}")
        return t
    except Exception as e:  # noqa: BLE001 - any damage: render again
        warnings.warn(f"{path}: template cache unreadable ({e}); rendering the templates again", RuntimeWarning,
                      stacklevel=3)
        return None

"""The table of annotated instances of a BOP split, shared by the pose and detection datasets.

Built once from ``scene_camera.json``, ``scene_gt.json`` and ``scene_gt_info.json`` (no image is
read), held as flat numpy arrays so that DataLoader workers copy little. Also: reading an image's
masks, and the by-image train/validation split.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, TypeVar, overload

import numpy as np

from cosy_lite.bop import io
from cosy_lite.bop.dataset import BopDataset
from cosy_lite.errors import BopFormatError, ConfigError


@dataclass
class InstanceTable:
    """Every GT instance of a split (M images, N instances). Poses in metres, boxes xyxy pixels."""

    split: str
    scene_ids: np.ndarray  # [M] int64
    im_ids: np.ndarray  # [M] int64
    K: np.ndarray  # [M,3,3] float32
    n_gt: np.ndarray  # [M] int64 number of entries in scene_gt for the image
    image_idx: np.ndarray  # [N] int64 row in the image arrays
    gt_idx: np.ndarray  # [N] int64 index in the image's scene_gt list
    obj_ids: np.ndarray  # [N] int64
    TCO: np.ndarray  # [N,4,4] float32 [m]
    bbox_visib: np.ndarray  # [N,4] float32 xyxy [px], x1 = x + w
    visib_fract: np.ndarray  # [N] float32
    px_count_visib: np.ndarray  # [N] int64

    def __len__(self) -> int:
        return len(self.gt_idx)

    def select(self, obj_ids: list[int] | None, min_visib_fract: float, min_px: int) -> np.ndarray:
        """Boolean [N]: instances of ``obj_ids`` (None: all) with visib_fract >= min_visib_fract and
        at least ``min_px`` visible pixels."""
        keep = (self.visib_fract >= min_visib_fract) & (self.px_count_visib >= min_px)
        if obj_ids is not None:
            keep &= np.isin(self.obj_ids, np.asarray(list(obj_ids), dtype=np.int64))
        return keep

    def image_keys(self) -> list[tuple[int, int]]:
        return list(zip(self.scene_ids.tolist(), self.im_ids.tolist()))


def scan_split(dataset: BopDataset, split: str, scene_ids: list[int] | None = None) -> InstanceTable:
    """Read the scene files of ``split`` into an :class:`InstanceTable`.

    Raises BopFormatError when ``scene_gt_info.json`` is missing or disagrees with ``scene_gt.json``.
    """
    img_rows: list[tuple[int, int, np.ndarray, int]] = []
    inst: dict[str, list] = {k: [] for k in ("image_idx", "gt_idx", "obj_ids", "TCO", "bbox_visib", "visib_fract", "px")}
    for scene_id in dataset.scene_ids(split) if scene_ids is None else scene_ids:
        sdir = dataset.scene_dir(split, scene_id)
        cams = dataset.scene_camera(split, scene_id)
        gts = dataset.scene_gt(split, scene_id)
        infos = dataset.scene_gt_info(split, scene_id)
        if infos is None:
            raise BopFormatError(sdir / "scene_gt_info.json", "", "file not found (needed for bbox_visib and visib_fract)")
        for im_id in sorted(cams):
            gt, info = gts.get(im_id, []), infos.get(im_id, [])
            if len(gt) != len(info):
                raise BopFormatError(sdir / "scene_gt_info.json", str(im_id),
                                     f"{len(info)} entries but scene_gt.json has {len(gt)}")
            row = len(img_rows)
            img_rows.append((scene_id, im_id, cams[im_id].K, len(gt)))
            for k, (g, i) in enumerate(zip(gt, info)):
                x, y, w, h = i.bbox_visib
                inst["image_idx"].append(row)
                inst["gt_idx"].append(k)
                inst["obj_ids"].append(g.obj_id)
                inst["TCO"].append(g.TCO)
                inst["bbox_visib"].append((x, y, x + w, y + h))
                inst["visib_fract"].append(i.visib_fract)
                inst["px"].append(i.px_count_visib)
    n = len(inst["gt_idx"])
    return InstanceTable(
        split=split,
        scene_ids=np.array([r[0] for r in img_rows], dtype=np.int64),
        im_ids=np.array([r[1] for r in img_rows], dtype=np.int64),
        K=np.array([r[2] for r in img_rows], dtype=np.float32).reshape(-1, 3, 3),
        n_gt=np.array([r[3] for r in img_rows], dtype=np.int64),
        image_idx=np.array(inst["image_idx"], dtype=np.int64),
        gt_idx=np.array(inst["gt_idx"], dtype=np.int64),
        obj_ids=np.array(inst["obj_ids"], dtype=np.int64),
        TCO=np.array(inst["TCO"], dtype=np.float32).reshape(n, 4, 4),
        bbox_visib=np.array(inst["bbox_visib"], dtype=np.float32).reshape(n, 4),
        visib_fract=np.array(inst["visib_fract"], dtype=np.float32),
        px_count_visib=np.array(inst["px"], dtype=np.int64),
    )


@overload
def check_obj_ids(dataset: BopDataset, obj_ids: list[int]) -> list[int]: ...
@overload
def check_obj_ids(dataset: BopDataset, obj_ids: None) -> None: ...
@overload
def check_obj_ids(dataset: BopDataset, obj_ids: list[int] | None) -> list[int] | None: ...
def check_obj_ids(dataset: BopDataset, obj_ids: list[int] | None) -> list[int] | None:
    """``obj_ids`` as a sorted list, each checked against ``models_info.json`` (None stays None)."""
    if obj_ids is None:
        return None
    unknown = sorted(set(obj_ids) - set(dataset.obj_ids))
    if unknown:
        raise BopFormatError(dataset.models_dir / "models_info.json", "obj_id",
                             f"obj_ids {unknown} not in the dataset (known: {dataset.obj_ids})")
    return sorted(set(obj_ids))


def load_rgb(dataset: BopDataset, split: str, scene_id: int, im_id: int) -> np.ndarray:
    """RGB uint8 [H,W,3]; BopFormatError naming the file if it is missing or unreadable."""
    return io.load_image(dataset.rgb_path(split, scene_id, im_id))


def load_masks(dataset: BopDataset, split: str, scene_id: int, im_id: int, gt_indices: list[int],
               shape: tuple[int, int]) -> np.ndarray:
    """Visible masks (``mask_visib``) of the given GT indices, bool [len(gt_indices),H,W].

    BopFormatError naming the file if one is missing, unreadable or not of size ``shape`` (H, W).
    """
    out = np.zeros((len(gt_indices), *shape), dtype=bool)
    for j, k in enumerate(gt_indices):
        path = dataset.mask_path(split, scene_id, im_id, int(k), visib=True)
        m = io.load_mask(path)
        if m.shape != tuple(shape):
            raise BopFormatError(path, "shape", f"mask is {m.shape[1]}x{m.shape[0]}, the image is {shape[1]}x{shape[0]}")
        out[j] = m
    return out


# ----------------------------------------------------------------------------- train / validation split


class ImageIndexed(Protocol):
    """A dataset made of whole images, which can be restricted to some of them."""

    def image_keys(self) -> list[tuple[int, int]]: ...  # (scene_id, im_id) of the images it uses

    def select_images(self, keys: set[tuple[int, int]]): ...  # a copy restricted to those images


D = TypeVar("D", bound=ImageIndexed)


def split_train_val(dataset: D, val_fraction: float | None = None, n_val_images: int | None = None,
                    seed: int = 0) -> tuple[D, D]:
    """Split by IMAGE: the validation images are never in the training part.

    Give exactly one of ``val_fraction`` (of the images, rounded, at least 1 if the fraction is
    > 0) or ``n_val_images``. The choice is a seeded permutation of the sorted image keys.
    """
    if (val_fraction is None) == (n_val_images is None):
        raise ValueError("split_train_val: give exactly one of val_fraction and n_val_images")
    keys = sorted(set(dataset.image_keys()))
    if val_fraction is not None:
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"split_train_val: val_fraction must be in [0, 1), got {val_fraction}")
        n_val = max(1, round(val_fraction * len(keys))) if val_fraction > 0 else 0
    else:
        assert n_val_images is not None  # exactly one of the two is given (checked above)
        n_val = int(n_val_images)
    if not 0 <= n_val < len(keys):
        raise ValueError(f"split_train_val: cannot hold out {n_val} of {len(keys)} images and keep some for training")
    order = np.random.default_rng(seed).permutation(len(keys))
    val = {keys[i] for i in order[:n_val]}
    train = set(keys) - val
    return dataset.select_images(train), dataset.select_images(val)


def hold_out_images(dataset: D, n_val_images: int, seed: int, split_dir: str) -> tuple[D, D]:
    """:func:`split_train_val` for a training command: too few images is a :class:`ConfigError`.

    The message names ``data.val_images`` and the split folder (``split_dir``), so that a user with a
    small dataset of their own learns which setting to lower instead of reading a traceback.
    """
    n_images = len(set(dataset.image_keys()))
    if n_images == 0:
        raise ConfigError(split_dir, "", "no image of this split has a usable instance (check the "
                          "objects, data.min_visib_fract and the split's scene_gt*.json)")
    if not 0 <= n_val_images < n_images:
        raise ConfigError("config", "data.val_images",
                          f"{n_val_images} images held out for validation, but {split_dir} has only "
                          f"{n_images} usable image(s); set data.val_images=N with N < {n_images} "
                          f"(at least one image must remain for training)")
    return split_train_val(dataset, n_val_images=n_val_images, seed=seed)

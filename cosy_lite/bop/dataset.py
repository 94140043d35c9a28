"""A BOP dataset on disk: paths, cached scene files, iteration over images.

Layout (BOP format): ``ROOT/models``, ``ROOT/models_eval``, ``ROOT/<split>/<scene:06d>/...`` and
``ROOT/test_targets_bop19.json`` (+ ``test_targets_bop24.json``). All values returned are in metres (see :mod:`cosy_lite.bop.io`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import numpy as np

from cosy_lite.bop import io
from cosy_lite.bop.params import DatasetParams, SplitParams, dataset_name_of, get_dataset_params
from cosy_lite.errors import BopFormatError

if TYPE_CHECKING:
    import trimesh

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


@dataclass
class ImageRecord:
    """Everything known about one image of a split (metres)."""

    split: str
    scene_id: int
    im_id: int
    camera: io.CameraRecord
    gt: list[io.GtPose]
    gt_info: list[io.GtInfo] | None
    rgb_path: Path
    depth_path: Path | None


@dataclass
class BopDataset:
    """Access to one BOP dataset folder.

    Args:
        root: the dataset folder (contains ``models/``).
        name: key into the dataset parameter table; defaults to the folder name.
    """

    root: Path
    name: str = ""
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        self.name = dataset_name_of(self.root, self.name)
        if not self.root.is_dir():
            from cosy_lite.bop.folders import where_datasets_are

            raise BopFormatError(self.root, "", f"dataset folder not found ({where_datasets_are()})")

    # ------------------------------------------------------------------ static facts
    @cached_property
    def params(self) -> DatasetParams:
        return get_dataset_params(self.name)

    def split_params(self, split: str) -> SplitParams | None:
        """Parameters of ``split`` if the dataset and split are in the table, else None."""
        from cosy_lite.bop.params import DATASETS

        p = DATASETS.get(self.name)
        return p.splits.get(split) if p is not None else None

    # ------------------------------------------------------------------ models
    @property
    def models_dir(self) -> Path:
        return self.root / "models"

    @property
    def models_eval_dir(self) -> Path:
        return self.root / "models_eval"

    @cached_property
    def models_info(self) -> dict[int, io.ModelInfo]:
        return io.load_models_info(self.models_dir / "models_info.json")

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self.models_info)

    def model_path(self, obj_id: int, eval: bool = False) -> Path:
        self._check_obj_id(obj_id)
        return (self.models_eval_dir if eval else self.models_dir) / f"obj_{obj_id:06d}.ply"

    def load_model(self, obj_id: int, eval: bool = False) -> trimesh.Trimesh:
        """trimesh.Trimesh in metres (``eval=True``: from ``models_eval/``)."""
        return io.load_model(self.model_path(obj_id, eval))

    def load_model_geometry(self, obj_id: int, eval: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(vertices [N,3] m, faces [F,3]) of the model (``eval=True``: from ``models_eval/``), without trimesh."""
        return io.load_model_geometry(self.model_path(obj_id, eval))

    def _check_obj_id(self, obj_id: int) -> None:
        if obj_id not in self.models_info:
            raise BopFormatError(self.models_dir / "models_info.json", str(obj_id),
                                 f"obj_id {obj_id} not in models_info (known: {self.obj_ids})")

    # ------------------------------------------------------------------ splits and scenes
    def split_dir(self, split: str) -> Path:
        return self.root / split

    def scene_dir(self, split: str, scene_id: int) -> Path:
        return self.split_dir(split) / f"{scene_id:06d}"

    def scene_ids(self, split: str) -> list[int]:
        d = self.split_dir(split)
        if not d.is_dir():
            raise BopFormatError(d, "", f"split folder not found (splits present: {self.available_splits()})")
        return sorted(int(p.name) for p in d.iterdir() if p.is_dir() and p.name.isdigit())

    def available_splits(self) -> list[str]:
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(("models", ".")))

    def scene_camera(self, split: str, scene_id: int) -> dict[int, io.CameraRecord]:
        return self._cached(
            ("cam", split, scene_id), lambda: io.load_scene_camera(self.scene_dir(split, scene_id) / "scene_camera.json")
        )

    def scene_gt(self, split: str, scene_id: int) -> dict[int, list[io.GtPose]]:
        valid = set(self.obj_ids)
        return self._cached(
            ("gt", split, scene_id), lambda: io.load_scene_gt(self.scene_dir(split, scene_id) / "scene_gt.json", valid)
        )

    def scene_gt_info(self, split: str, scene_id: int) -> dict[int, list[io.GtInfo]] | None:
        path = self.scene_dir(split, scene_id) / "scene_gt_info.json"
        if not path.is_file():
            return None
        return self._cached(("gt_info", split, scene_id), lambda: io.load_scene_gt_info(path))

    def _cached(self, key, fn):
        if key not in self._cache:
            self._cache[key] = fn()
        return self._cache[key]

    # ------------------------------------------------------------------ per-image paths
    def _find_image(self, folder: Path, im_id: int, preferred: str) -> Path:
        p = folder / f"{im_id:06d}{preferred}"
        if p.is_file():
            return p
        for ext in IMAGE_EXTS:
            q = folder / f"{im_id:06d}{ext}"
            if q.is_file():
                return q
        return p  # the expected path; the reader reports it missing

    def rgb_path(self, split: str, scene_id: int, im_id: int) -> Path:
        sp = self.split_params(split) or SplitParams((0, 0))
        sub = "gray" if sp.gray else "rgb"
        return self._find_image(self.scene_dir(split, scene_id) / sub, im_id, sp.rgb_ext)

    def depth_path(self, split: str, scene_id: int, im_id: int) -> Path:
        sp = self.split_params(split) or SplitParams((0, 0))
        return self._find_image(self.scene_dir(split, scene_id) / "depth", im_id, sp.depth_ext)

    def mask_path(self, split: str, scene_id: int, im_id: int, gt_idx: int, visib: bool = False) -> Path:
        sub = "mask_visib" if visib else "mask"
        return self.scene_dir(split, scene_id) / sub / f"{im_id:06d}_{gt_idx:06d}.png"

    def image_ids(self, split: str, scene_id: int) -> list[int]:
        return sorted(self.scene_camera(split, scene_id))

    def image(self, split: str, scene_id: int, im_id: int) -> ImageRecord:
        cams = self.scene_camera(split, scene_id)
        if im_id not in cams:
            raise BopFormatError(self.scene_dir(split, scene_id) / "scene_camera.json", str(im_id), "image id not present")
        gts = self.scene_gt(split, scene_id) if (self.scene_dir(split, scene_id) / "scene_gt.json").is_file() else {}
        infos = self.scene_gt_info(split, scene_id)
        depth = self.depth_path(split, scene_id, im_id)
        return ImageRecord(
            split, scene_id, im_id, cams[im_id], gts.get(im_id, []),
            infos.get(im_id) if infos is not None else None,
            self.rgb_path(split, scene_id, im_id), depth if depth.is_file() else None,
        )

    def images(self, split: str) -> Iterator[ImageRecord]:
        for scene_id in self.scene_ids(split):
            for im_id in self.image_ids(split, scene_id):
                yield self.image(split, scene_id, im_id)

    def load_rgb(self, rec: ImageRecord) -> np.ndarray:
        return io.load_image(rec.rgb_path)

    def load_depth(self, rec: ImageRecord) -> np.ndarray:
        if rec.depth_path is None:
            raise BopFormatError(self.depth_path(rec.split, rec.scene_id, rec.im_id), "", "depth file not found")
        return io.load_depth(rec.depth_path, rec.camera.depth_scale)

    # ------------------------------------------------------------------ test targets
    @property
    def test_targets_path(self) -> Path:
        return self.root / "test_targets_bop19.json"

    def test_targets(self) -> list[io.Target]:
        return io.load_test_targets(self.test_targets_path, set(self.obj_ids))

    @property
    def test_targets_bop24_path(self) -> Path:
        return self.root / "test_targets_bop24.json"

    def test_image_targets(self) -> list[io.ImageTarget]:
        """The images of ``test_targets_bop24.json`` (BOP 2024/2025 6D detection), in file order."""
        return io.load_image_targets(self.test_targets_bop24_path)

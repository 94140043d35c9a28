"""Instances as the start stage sees them, computed once: what the coarse scorer trains on.

For each GT instance (its visible mask standing in for a detection): the crop that
:func:`~cosy_lite.nets.appearance_templates.detection_crop` cuts (uint8), the silhouette soft IoU
of each of its object's templates, and each template pose's rotation error to GT (deg,
symmetry-aware), the pose placed on the detection exactly as inference places it
(:meth:`SilhouetteTemplates.observe` / ``poses``). ~80 ms per instance on one core, so each scene
of a split is described once and cached as its own ``.npz`` (no pickle), keyed by the dataset folder,
split, instance selection, template settings and the scene's instances themselves
(:func:`observations_by_scene`): a split that gains scenes describes only the new ones, and a
regenerated scene is described again.
"""

from __future__ import annotations

import hashlib
import multiprocessing as mp
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, Sequence

import numpy as np
import torch
from torch import Tensor

from cosy_lite.geometry.symmetries import rotation_errors_deg
from cosy_lite.nets.appearance_templates import CROP_SIZE, detection_crop
from cosy_lite.nets.silhouette_templates import SilhouetteTemplates, mask_boxes

if TYPE_CHECKING:
    from cosy_lite.data.pose_dataset import PoseDataset
    from cosy_lite.structures import PoseSample

FIELDS = ("obj_ids", "crops", "iou", "errors_deg", "items")


class Instances(Protocol):
    """What is described: GT instances by index (e.g. :class:`~cosy_lite.data.pose_dataset.PoseDataset`)."""

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> PoseSample: ...

    def fingerprint(self) -> str: ...


@dataclass
class StartObservations:
    """``obj_ids [M]`` int64, ``crops [M,3,S,S]`` uint8, ``iou [M,N]`` and ``errors_deg [M,N]`` float16
    (N: templates per object), ``items [M]`` int64: the index of each row's instance in what was
    described (instances that cannot be observed have no row)."""

    obj_ids: Tensor
    crops: Tensor
    iou: Tensor
    errors_deg: Tensor
    items: Tensor

    def __len__(self) -> int:
        return len(self.obj_ids)

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
        np.savez(tmp, **{f: getattr(self, f).numpy() for f in FIELDS})
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: Path) -> "StartObservations | None":
        """The observations at ``path``; None when absent or damaged (then computed again)."""
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as f:
                obs = cls(*(torch.from_numpy(f[k]) for k in FIELDS))
            m = len(obs.obj_ids)
            if not (len(obs.crops) == len(obs.iou) == len(obs.errors_deg) == len(obs.items) == m
                    and obs.crops.dtype == torch.uint8):
                raise ValueError("fields of different lengths or types")
            return obs
        except Exception as e:  # noqa: BLE001 - any damage: compute again
            warnings.warn(f"{path}: start observations unreadable ({e}); computing them again", RuntimeWarning,
                          stacklevel=2)
            return None


def observe(instance: PoseSample, templates: SilhouetteTemplates,
            symmetries: np.ndarray) -> tuple[Tensor, np.ndarray, np.ndarray] | None:
    """(crop uint8 [3,S,S], iou [N], errors_deg [N]) of one :class:`~cosy_lite.structures.PoseSample`
    (``rgb``, ``mask``, ``K``, ``TCO``, ``obj_id``); ``symmetries [S,3,3]`` of its object. None when its
    mask is empty or the turned camera does not see it."""
    mask = instance.mask.numpy().astype(bool)
    K = instance.K.double().numpy()
    box = mask_boxes(mask[None])[0]
    if not np.isfinite(box).all():
        return None
    view = templates.observe(mask, box, K)
    if view is None:
        return None
    rgb = instance.rgb.permute(1, 2, 0).numpy()
    crop = (detection_crop(rgb, view, K) * 255).round().to(torch.uint8)
    t = templates.templates(instance.obj_id)
    iou = templates.silhouette_iou(t, view.grid)
    poses = templates.poses(t, np.arange(len(t.rotations)), view, K)
    errors = rotation_errors_deg(poses[:, :3, :3], instance.TCO[:3, :3].double().numpy(), symmetries)
    return crop, iou, errors


def observe_all(instances: Instances, templates: SilhouetteTemplates, symmetries: dict[int, np.ndarray],
                desc: str = "start observations", progress: bool = True, workers: int = 1) -> StartObservations:
    """:func:`observe` for every item of ``instances`` (a dataset of PoseSamples); ``symmetries``:
    obj_id -> ``[S,3,3]``. Instances that cannot be observed are left out. ``workers`` > 1: that many
    forked processes share the work (the templates are rendered first, in this process, so that the
    workers only read images and compare masks); the result is the same as with one."""
    from tqdm import tqdm

    n = len(instances)
    bar = tqdm(total=n, desc=desc, unit="instance", disable=not progress)
    if workers > 1 and n > 1 and "fork" in mp.get_all_start_methods():
        for obj_id in symmetries:
            templates.templates(obj_id)  # rendered (or read) once, before the fork
        chunks = [range(s, min(s + _CHUNK, n)) for s in range(0, n, _CHUNK)]
        with mp.get_context("fork").Pool(workers, _worker_start, (instances, templates, symmetries)) as pool:
            parts = []
            for part in pool.imap(_observe_chunk, chunks):
                parts.append(part)
                bar.update(len(part[0]) + part[4])
    else:
        parts = [_observe_range(instances, templates, symmetries, range(n), bar)]
    bar.close()
    ids = [i for p in parts for i in p[0]]
    if not ids:
        return _empty(templates.n_rotations)
    crops, ious, errors = (torch.from_numpy(np.stack([x for p in parts for x in p[f]])) for f in (1, 2, 3))
    items = torch.tensor([i for p in parts for i in p[5]], dtype=torch.long)
    return StartObservations(torch.tensor(ids), crops, ious, errors, items)


def _empty(n_templates: int, m: int = 0) -> StartObservations:
    """``m`` rows of zeros (to be filled)."""
    return StartObservations(torch.zeros(m, dtype=torch.long), torch.zeros((m, 3, CROP_SIZE, CROP_SIZE), dtype=torch.uint8),
                             torch.zeros((m, n_templates), dtype=torch.half), torch.zeros((m, n_templates), dtype=torch.half),
                             torch.zeros(m, dtype=torch.long))


_CHUNK = 64  # instances per task of a worker
# (instances, templates, symmetries) of a forked worker
_SHARED: tuple[Any, SilhouetteTemplates, dict[int, np.ndarray]] | tuple[()] = ()


def _worker_start(instances: Instances, templates: SilhouetteTemplates, symmetries: dict[int, np.ndarray]) -> None:
    global _SHARED
    torch.set_num_threads(1)
    _SHARED = (instances, templates, symmetries)


def _observe_chunk(index: range) -> tuple:
    assert _SHARED, "set by _worker_start, the initializer of every worker"
    return _observe_range(*_SHARED, index, None)


def _observe_range(instances: Instances, templates: SilhouetteTemplates, symmetries: dict[int, np.ndarray],
                   index: range, bar: Any) -> tuple[list, list, list, list, int, list]:
    """(obj_ids, crops, ious, errors, number left out, items) of the instances ``index`` (numpy arrays:
    they travel back from a worker without torch's shared-memory handles)."""
    ids, crops, ious, errors, skipped, items = [], [], [], [], 0, []
    for i in index:
        item = instances[i]
        seen = observe(item, templates, symmetries[int(item.obj_id)])
        if bar is not None:
            bar.update(1)
        if seen is None:
            skipped += 1
            continue
        ids.append(int(item.obj_id))
        crops.append(seen[0].numpy())
        ious.append(seen[1].astype(np.float16))
        errors.append(seen[2].astype(np.float16))
        items.append(i)
    return ids, crops, ious, errors, skipped, items


def cache_key(*parts: Any) -> str:
    """A short hash of the settings that decide the observations."""
    return hashlib.sha256("|".join(str(p) for p in parts).encode()).hexdigest()[:20]


def observations_by_scene(instances: PoseDataset, parts: Sequence[PoseDataset], templates: SilhouetteTemplates,
                          symmetries: dict[int, np.ndarray], cache: Path, key: tuple, desc: str = "describe instances",
                          progress: bool = True, workers: int = 1) -> list[StartObservations]:
    """The observations of each of ``parts`` (image subsets of ``instances``, e.g. the training and
    the held-out images), in the order of their items.

    Each scene of ``instances`` is described once (:func:`observe_all`, the scenes not cached yet
    together) and kept in its own file of ``cache``, named by ``key`` (the settings that decide the
    observations), the scene and the fingerprint of its instances: a split that gains scenes describes
    only those, and any other change to a scene describes it again. The parts are assembled from the
    scenes' files in two passes (which rows, then the rows), so the memory holds each part once."""
    scenes = {}
    for scene_id in sorted({s for s, _ in instances.image_keys()}):
        sub = instances.select_scenes({scene_id})
        scenes[scene_id] = (sub, cache / f"start_observations_scene{scene_id:06d}_"
                                          f"{cache_key(*key, scene_id, sub.fingerprint())}.npz")
    selected: dict[int, list[np.ndarray]] = {}  # scene -> per part: the rows of the scene's file it takes
    missing = []
    for scene_id, (sub, path) in scenes.items():  # first pass: what each cached scene gives each part
        cached = StartObservations.load(path)
        if cached is None:
            missing.append(scene_id)
        else:
            selected[scene_id] = _rows_of_parts(sub.index[cached.items.numpy()], parts)
        del cached
    if missing:
        todo = instances.select_scenes(set(missing))
        obs = observe_all(todo, templates, symmetries, desc=f"{desc} ({len(missing)} of {len(scenes)} scenes)",
                          progress=progress, workers=workers)
        rows = todo.index[obs.items.numpy()]  # rows of the instance table
        for scene_id in missing:
            sub, path = scenes[scene_id]
            mine = np.isin(rows, sub.index)
            picked = _take(obs, torch.from_numpy(np.nonzero(mine)[0]))
            picked.items = torch.from_numpy(np.searchsorted(sub.index, rows[mine]))  # the item in the scene
            picked.save(path)
            selected[scene_id] = _rows_of_parts(rows[mine], parts)
        del obs
    out = [_empty(templates.n_rotations, sum(len(selected[s][k]) for s in scenes)) for k in range(len(parts))]
    start = [0] * len(parts)
    for scene_id, (sub, path) in scenes.items():  # second pass: the rows, into each part's tensors
        scene = StartObservations.load(path)
        if scene is None:
            raise RuntimeError(f"{path}: start observations removed or damaged while they were read")
        rows = sub.index[scene.items.numpy()]
        for k, part in enumerate(parts):
            take = selected[scene_id][k]
            end = start[k] + len(take)
            for f in FIELDS[:-1]:
                getattr(out[k], f)[start[k]:end] = getattr(scene, f)[torch.from_numpy(take)]
            out[k].items[start[k]:end] = torch.from_numpy(np.searchsorted(part.index, rows[take]))  # the item in the part
            start[k] = end
    return out


def _take(obs: StartObservations, rows: Tensor) -> StartObservations:
    return StartObservations(*(getattr(obs, f)[rows] for f in FIELDS))


def _rows_of_parts(rows: np.ndarray, parts: Sequence[PoseDataset]) -> list[np.ndarray]:
    """Per part, the positions in ``rows`` (instance-table rows, in a scene file's order) of its items."""
    return [np.nonzero(np.isin(rows, part.index))[0] for part in parts]

"""The embedded synthetic BOP dataset generator (in the spirit of BlenderProc4BOP, paper Sec. 3.2).

Per layout: a random subset of the dataset's objects plus distractors is dropped into a box and
settled by MuJoCo; the room gets random textures, lights and materials; ``views_per_layout``
cameras look at objects near the centre. Output in the BOP layout, ``train_pbr`` in chunks of
``chunk_size`` images, ``test`` one scene per layout, plus ``test_targets_bop19.json`` and
``test_targets_bop24.json``.

Deterministic per seed: each layout draws from its own ``SeedSequence((seed, split, layout))``,
so the worker count does not change the result. Resumable: finished chunks are skipped.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosy_lite.bop import io
from cosy_lite.bop.gt_info import compute_gt_info, projected_bbox
from cosy_lite.synth.cameras import CameraConfig, sample_camera_poses, ycbv_intrinsics
from cosy_lite.synth.distractors import DISTRACTORS, load_distractor_mesh
from cosy_lite.synth.layout import LayoutConfig, prepare_collision_shape, settle_objects
from cosy_lite.synth.scene_render import LightingConfig, PlacedMesh, SceneRenderer

SPLIT_CODES = {"train_pbr": 0, "test": 1}


@dataclass
class SplitConfig:
    n_images: int
    views_per_layout: int
    rgb_ext: str


@dataclass
class SynthConfig:
    """What to generate. Defaults = the default dataset ``ycbvsynth``."""

    name: str = "ycbvsynth"
    obj_ids: list[int] = field(default_factory=lambda: list(range(1, 22)))
    seed: int = 0
    train: SplitConfig = field(default_factory=lambda: SplitConfig(n_images=1000, views_per_layout=25, rgb_ext=".jpg"))
    test: SplitConfig = field(default_factory=lambda: SplitConfig(n_images=100, views_per_layout=10, rgb_ext=".png"))
    objects_per_layout: list[int] = field(default_factory=lambda: [8, 12])  # [min, max], without repetition
    distractors_per_layout: list[int] = field(default_factory=lambda: [2, 4])
    chunk_size: int = 1000  # images per train_pbr scene folder, as BOP PBR data
    depth_scale: float = 0.1  # depth PNG value * depth_scale = mm (BOP PBR convention)
    jpeg_quality: int = 95
    min_visib_fract_target: float = 0.1  # BOP19 test targets
    visib_delta: float = 0.015  # metres
    workers: int = 1
    models_dir: str | None = None  # your own meshes instead of the YCB-V library (cosy_lite.synth.custom_objects)
    models_units: str = "mm"  # of the meshes in models_dir: mm or m (checked for plausibility)
    layout: LayoutConfig = field(default_factory=LayoutConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    lighting: LightingConfig = field(default_factory=LightingConfig)

    def split_config(self, split: str) -> SplitConfig:
        return {"train_pbr": self.train, "test": self.test}[split]


@dataclass
class LayoutTask:
    split: str
    layout_idx: int
    scene_id: int
    first_im_id: int
    n_views: int


# ----------------------------------------------------------------------------- per-process state

_STATE: dict = {}


def _worker_state(cfg: SynthConfig, root: Path) -> dict:
    """Meshes, collision shapes and the GL renderer, built once per process."""
    key = (str(root), tuple(cfg.obj_ids))
    if _STATE.get("key") == key:
        return _STATE
    from cosy_lite.bop.io import load_model

    _STATE.clear()
    meshes = {f"obj_{i}": load_model(root / "models" / f"obj_{i:06d}.ply") for i in cfg.obj_ids}
    for name in DISTRACTORS:
        meshes[name] = load_distractor_mesh(name)
    w, h = ycbv_intrinsics()[1]
    _STATE.update(
        key=key,
        meshes=meshes,
        shapes={k: prepare_collision_shape(m) for k, m in meshes.items()},
        eval_vertices={i: np.asarray(meshes[f"obj_{i}"].vertices) for i in cfg.obj_ids},
        renderer=SceneRenderer(w, h),
    )
    return _STATE


def layout_rng(seed: int, split: str, layout_idx: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, SPLIT_CODES[split], layout_idx]))


def render_layout(cfg: SynthConfig, root: Path, task: LayoutTask) -> dict[int, tuple]:
    """Settle, render and annotate one layout; writes its images, returns per-image records."""
    st = _worker_state(cfg, root)
    rng = layout_rng(cfg.seed, task.split, task.layout_idx)
    lo, hi = cfg.objects_per_layout
    n_obj = min(int(rng.integers(lo, hi + 1)), len(cfg.obj_ids))
    obj_ids = [int(i) for i in rng.choice(cfg.obj_ids, size=n_obj, replace=False)]
    dlo, dhi = cfg.distractors_per_layout
    distractors = [DISTRACTORS[i] for i in rng.choice(len(DISTRACTORS), size=int(rng.integers(dlo, dhi + 1)), replace=False)]
    keys = [f"obj_{i}" for i in obj_ids] + distractors
    T_WOs = settle_objects([st["shapes"][k] for k in keys], rng, cfg.layout)
    placed = [PlacedMesh(k, st["meshes"][k], T, annotated=k.startswith("obj_")) for k, T in zip(keys, T_WOs)]

    K, _ = ycbv_intrinsics()
    annotated_pos = np.array([T[:3, 3] for p, T in zip(placed, T_WOs) if p.annotated])
    T_CWs = sample_camera_poses(annotated_pos, task.n_views, rng, cfg.camera)
    views = st["renderer"].render_views(placed, T_CWs, K, rng, cfg.lighting)

    split_cfg = cfg.split_config(task.split)
    scene_dir = root / task.split / f"{task.scene_id:06d}"
    records = {}
    for v, (T_CW, (rgb, depth, obj_depths)) in enumerate(zip(T_CWs, views)):
        im_id = task.first_im_id + v
        io.save_image(scene_dir / "rgb" / f"{im_id:06d}{split_cfg.rgb_ext}", rgb, cfg.jpeg_quality)
        # Quantise once; annotate against the depth exactly as stored, as the BOP toolkit would.
        depth_png = io.depth_to_png_units(depth, cfg.depth_scale)
        io.save_depth_png(scene_dir / "depth" / f"{im_id:06d}.png", depth_png)
        depth_stored = depth_png.astype(np.float32) * np.float32(cfg.depth_scale * io.MM)
        gts, infos = [], []
        for gt_idx, (obj_id, obj_depth) in enumerate(zip(obj_ids, obj_depths)):
            TCO = T_CW @ T_WOs[gt_idx]
            bbox_obj = projected_bbox(st["eval_vertices"][obj_id], TCO, K)
            mask, mask_visib, info = compute_gt_info(depth_stored, obj_depth, K, bbox_obj, cfg.visib_delta)
            io.save_mask(scene_dir / "mask" / f"{im_id:06d}_{gt_idx:06d}.png", mask)
            io.save_mask(scene_dir / "mask_visib" / f"{im_id:06d}_{gt_idx:06d}.png", mask_visib)
            gts.append(io.GtPose(obj_id, TCO))
            infos.append(info)
        records[im_id] = (io.CameraRecord(K, cfg.depth_scale, T_CW), gts, infos)
    return records


def _render_layout_job(args: tuple) -> dict[int, tuple]:
    return render_layout(*args)


# ----------------------------------------------------------------------------- orchestration


def plan_split(cfg: SynthConfig, split: str) -> dict[int, list[LayoutTask]]:
    """scene_id -> its layouts. train_pbr: chunks of ``chunk_size`` images; test: one scene per layout."""
    sc = cfg.split_config(split)
    plan: dict[int, list[LayoutTask]] = {}
    done, layout_idx = 0, 0
    while done < sc.n_images:
        n = min(sc.views_per_layout, sc.n_images - done)
        if split == "train_pbr":
            scene_id, first = done // cfg.chunk_size, done % cfg.chunk_size
            n = min(n, cfg.chunk_size - first)
        else:
            scene_id, first = layout_idx, 0
        plan.setdefault(scene_id, []).append(LayoutTask(split, layout_idx, scene_id, first, n))
        done += n
        layout_idx += 1
    return plan


def scene_is_complete(scene_dir: Path, n_images: int) -> bool:
    path = scene_dir / "scene_gt_info.json"
    if not path.is_file():
        return False
    try:
        return len(io.load_json(path)) == n_images
    except Exception:
        return False


def write_camera_json(root: Path, cfg: SynthConfig) -> None:
    K, (w, h) = ycbv_intrinsics()
    io.save_json(root / "camera.json", {
        "cx": float(K[0, 2]), "cy": float(K[1, 2]), "depth_scale": cfg.depth_scale,
        "fx": float(K[0, 0]), "fy": float(K[1, 1]), "height": h, "width": w,
    })


def write_test_targets(root: Path, cfg: SynthConfig) -> list[io.Target]:
    """BOP19 targets: instances with visib_fract >= min_visib_fract_target, counted per (scene, image, object);
    BOP24 targets (6D detection): the images with at least one of them."""
    targets = []
    test_dir = root / "test"
    for scene_dir in sorted(p for p in test_dir.iterdir() if p.is_dir()):
        gts = io.load_scene_gt(scene_dir / "scene_gt.json")
        infos = io.load_scene_gt_info(scene_dir / "scene_gt_info.json")
        for im_id in sorted(gts):
            counts = Counter(g.obj_id for g, i in zip(gts[im_id], infos[im_id]) if i.visib_fract >= cfg.min_visib_fract_target)
            targets += [io.Target(int(scene_dir.name), im_id, o, c) for o, c in sorted(counts.items())]
    io.save_json(root / "test_targets_bop19.json", io.targets_to_json(targets))
    images = list(dict.fromkeys(io.ImageTarget(t.scene_id, t.im_id) for t in targets))  # images with a target
    io.save_json(root / "test_targets_bop24.json", io.image_targets_to_json(images))
    return targets


def generate(cfg: SynthConfig, root: str | Path, splits: tuple[str, ...] = ("train_pbr", "test"), progress: bool = True) -> dict:
    """Generate (or finish generating) the dataset in ``root``; returns timing statistics."""
    from tqdm import tqdm

    from cosy_lite.synth.objects import write_bop_models
    from cosy_lite.synth.ownership import check_can_write

    root = Path(root)
    if cfg.models_dir:
        from dataclasses import replace

        from cosy_lite.synth.custom_objects import find_meshes, write_custom_models

        sources = {o: (str(p.resolve()), cfg.models_units) for o, p in find_meshes(cfg.models_dir).items()}
        check_can_write(root, sources)  # never replaces a mesh of a folder made from other objects
        root.mkdir(parents=True, exist_ok=True)
        cfg = replace(cfg, obj_ids=sorted(write_custom_models(cfg.models_dir, cfg.models_units, root)))
    else:
        check_can_write(root, None, list(cfg.obj_ids))
        root.mkdir(parents=True, exist_ok=True)
        write_bop_models(cfg.obj_ids, root)
    write_camera_json(root, cfg)

    todo: list[tuple[Path, list[LayoutTask]]] = []
    for split in splits:
        for scene_id, tasks in plan_split(cfg, split).items():
            scene_dir = root / split / f"{scene_id:06d}"
            if not scene_is_complete(scene_dir, sum(t.n_views for t in tasks)):
                todo.append((scene_dir, tasks))
    n_images = sum(t.n_views for _, tasks in todo for t in tasks)
    stats = {"images": n_images, "seconds": 0.0}
    t0 = time.perf_counter()
    bar = tqdm(total=n_images, desc=f"generate {cfg.name}", unit="img", disable=not progress)
    ctx = mp.get_context("spawn")  # a forked child would inherit the parent's GL context and hang
    pool = ctx.Pool(cfg.workers) if cfg.workers > 1 else None
    try:
        for scene_dir, tasks in todo:
            cams, gts, infos = {}, {}, {}
            jobs = [(cfg, root, t) for t in tasks]
            results = pool.imap(_render_layout_job, jobs) if pool else map(_render_layout_job, jobs)
            for task, recs in zip(tasks, results):
                for im_id, (cam, gt, info) in recs.items():
                    cams[im_id], gts[im_id], infos[im_id] = cam, gt, info
                bar.update(task.n_views)
            io.save_json(scene_dir / "scene_camera.json", io.scene_camera_to_json(cams))
            io.save_json(scene_dir / "scene_gt.json", io.scene_gt_to_json(gts))
            io.save_json(scene_dir / "scene_gt_info.json", io.scene_gt_info_to_json(infos))  # last: marks the scene done
    finally:
        bar.close()
        if pool:
            pool.close()
            pool.join()
    if "test" in splits:
        write_test_targets(root, cfg)
    stats["seconds"] = time.perf_counter() - t0
    return stats

"""Validate a BOP dataset folder or a BOP19 results CSV, reporting every problem found.

Both checks return a list of :class:`Problem` (file, field, message, severity) and never stop at
the first one. Readers of :mod:`cosy_lite.bop.io` and :mod:`cosy_lite.bop.results` do the
per-file checks; this module adds the checks across files (ids, image files, sizes, units).
"""

from __future__ import annotations

import codecs
import math
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from cosy_lite.bop import io
from cosy_lite.bop.dataset import IMAGE_EXTS
from cosy_lite.bop.params import DATASETS, RENAMED_DATASETS, DatasetParams, SplitParams, dataset_name_of, renamed_dataset_message
from cosy_lite.bop.results import ResultRow, format_estimate, misread_dataset, parse_results_csv, parse_results_filename
from cosy_lite.errors import BopFormatError

Severity = Literal["error", "warning"]
SEVERITIES: tuple[str, ...] = ("error", "warning")
MODEL_DIRS = ("models", "models_eval")
SCENE_FILES = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json")
MASK_DIRS = ("mask", "mask_visib")
TARGETS_FILE = "test_targets_bop19.json"
TARGETS_BOP24_FILE = "test_targets_bop24.json"  # 6D detection: images only
UNIT_MIXUP_RATIO = 30.0  # model extent and diameter further apart than this: mm/m mix-up (~1000x)
DIAMETER_TOL = 0.05  # relative slack when comparing a diameter with the model's bounding box
MAX_LISTED = 10  # ids listed in one message
# PIL modes of a BOP depth image: single-channel 16-bit (an 8-bit PNG would be read as depth / 256).
DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I;16N", "I")


@dataclass
class Problem:
    """One thing wrong (``error``) or suspicious (``warning``) in a file."""

    path: str
    field: str  # JSON key / CSV "line N: column" / image property; "" for the whole file
    message: str
    severity: Severity = "error"

    def __post_init__(self) -> None:
        if self.severity not in SEVERITIES:
            raise ValueError(f"severity must be one of {SEVERITIES}, got {self.severity!r}")

    def __str__(self) -> str:
        where = self.path + (f" [{self.field}]" if self.field else "")
        return f"{self.severity.upper()} {where}: {' '.join(self.message.splitlines())}"

    @classmethod
    def from_error(cls, e: BopFormatError) -> Problem:
        return cls(e.path, e.field, e.problem, "error")


class _Collector:
    """Accumulates problems; ``load`` runs a reader and turns its failure into a problem."""

    def __init__(self) -> None:
        self.items: list[Problem] = []

    def error(self, path: str | Path, fld: str, message: str) -> None:
        self.items.append(Problem(str(path), fld, message, "error"))

    def warning(self, path: str | Path, fld: str, message: str) -> None:
        self.items.append(Problem(str(path), fld, message, "warning"))

    def load(self, reader: Callable[..., Any], path: Path, *args: Any) -> Any | None:
        try:
            return reader(path, *args)
        except BopFormatError as e:
            self.items.append(Problem.from_error(e))
        except Exception as e:  # unexpected structure the reader did not anticipate
            self.error(path, "", f"unreadable ({type(e).__name__}: {e})")
        return None


def _short(ids: list[int]) -> str:
    more = f" ... ({len(ids)} in all)" if len(ids) > MAX_LISTED else ""
    return ", ".join(str(i) for i in ids[:MAX_LISTED]) + more


def _kind(p: Problem) -> tuple[str, str, str, str]:
    """What makes two problems the same kind: file, severity, field and message but for their numbers."""
    return p.path, p.severity, re.sub(r"\d+", "#", p.field), re.sub(r"-?\d+(\.\d+)?", "#", p.message)


def summarised(problems: list[Problem]) -> list[Problem]:
    """``problems`` with the warnings of one kind (:func:`_kind`) merged into their first, which
    then gives their count and where the others are; errors stay one per line."""
    groups: dict[tuple[str, str, str, str], list[Problem]] = {}
    out: list[Problem | tuple] = []
    for p in problems:
        if p.severity == "warning":
            key = _kind(p)
            if key not in groups:
                out.append(key)
            groups.setdefault(key, []).append(p)
        else:
            out.append(p)
    merged: list[Problem] = []
    for item in out:
        if isinstance(item, Problem):
            merged.append(item)
            continue
        first, rest = groups[item][0], groups[item][1:]
        if rest:
            where = _short_texts([r.field or r.message for r in rest])
            first = Problem(first.path, first.field, f"{first.message} (and {len(rest)} more like it: {where})",
                            first.severity)
        merged.append(first)
    return merged


def _short_texts(texts: list[str]) -> str:
    more = f" ... ({len(texts)} in all)" if len(texts) > MAX_LISTED else ""
    return "; ".join(texts[:MAX_LISTED]) + more


def report(problems: list[Problem], subject: str) -> int:
    """Print one line per error and per kind of warning (:func:`summarised`), then a summary;
    return the exit code (1 if any error)."""
    for p in summarised(problems):
        print(p)
    n_err = sum(p.severity == "error" for p in problems)
    n_warn = len(problems) - n_err
    if n_err:
        print(f"FAILED {subject}: {n_err} errors, {n_warn} warnings")
        return 1
    print(f"OK {subject}: 0 errors, {n_warn} warnings")
    return 0


# ----------------------------------------------------------------------------- dataset: models


def _raw_diameters(info_path: Path) -> dict[int, float | None] | None:
    """Best-effort {obj_id: diameter in file units} when models_info.json fails the strict reader."""
    try:
        raw = io.load_json(info_path)
    except BopFormatError:
        return None
    if not isinstance(raw, dict):
        return None
    out: dict[int, float | None] = {}
    for key, d in raw.items():
        if not key.isdigit():
            continue
        v = d.get("diameter") if isinstance(d, dict) else None
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
            out[int(key)] = float(v)
        else:
            out[int(key)] = None
    return out or None


def _check_model_file(ply: Path, info_path: Path, obj_id: int, diameter_mm: float | None, out: _Collector) -> None:
    try:
        v, faces = io.read_model_arrays(ply)
    except BopFormatError as e:
        out.error(ply, e.field, e.problem)
        return
    if len(v) == 0:
        out.error(ply, "vertex", io.NO_MESH)
        return
    if not np.all(np.isfinite(v)):
        out.error(ply, "vertex", "vertices contain NaN or inf")
        return
    if (msg := io.faces_problem(faces, len(v))) is not None:
        out.error(ply, "face", msg)
        return
    sides = np.ptp(v, axis=0)
    diag = float(np.linalg.norm(sides))
    if diameter_mm is None:
        return
    ratio = diag / diameter_mm
    if not 1.0 / UNIT_MIXUP_RATIO < ratio < UNIT_MIXUP_RATIO:
        out.error(ply, "vertex", (
            f"model extent {diag:.4g} (bounding-box diagonal, file units) is {ratio:.3g}x the diameter "
            f"{diameter_mm:.4g} mm of obj_id {obj_id} in {info_path}: mm/m mix-up? BOP models and models_info are in mm"
        ))
    elif sides.max() > diameter_mm * (1 + DIAMETER_TOL) or diameter_mm > diag * (1 + DIAMETER_TOL):
        out.warning(info_path, f"{obj_id}.diameter", (
            f"{diameter_mm:.4g} mm does not fit {ply} (largest side {sides.max():.4g}, diagonal {diag:.4g}); "
            "expected the largest distance between two vertices"
        ))


def _check_models(root: Path, params: DatasetParams | None, out: _Collector,
                  model_dirs: tuple[str, ...] = MODEL_DIRS) -> set[int] | None:
    """Check models_info.json and the model files; return the obj ids (None if unknown)."""
    info_path = root / "models" / "models_info.json"
    infos = out.load(io.load_models_info, info_path)
    diameters: dict[int, float | None] | None
    if infos is not None:
        diameters = {i: m.diameter / io.MM for i, m in infos.items()}
    else:
        diameters = _raw_diameters(info_path)
        if diameters is None:
            return None
    obj_ids = set(diameters)
    if params is not None and (extra := sorted(obj_ids - set(params.obj_ids))):
        out.warning(info_path, "", f"obj_ids {_short(extra)} are not objects of {params.name} {list(params.obj_ids)}")
    for folder in model_dirs:
        d = root / folder
        if not d.is_dir():
            out.error(d, "", f"folder not found (BOP needs {folder}/obj_XXXXXX.ply for every obj_id of {info_path})")
            continue
        for obj_id in sorted(obj_ids):
            ply = d / f"obj_{obj_id:06d}.ply"
            if not ply.is_file():
                out.error(ply, "", f"model of obj_id {obj_id} (listed in {info_path}) not found")
                continue
            _check_model_file(ply, info_path, obj_id, diameters[obj_id], out)
    return obj_ids


# ----------------------------------------------------------------------------- dataset: scenes


@dataclass
class _SceneIndex:
    """What later checks (test targets) need to know about one scene."""

    im_ids: set[int] | None  # image ids of scene_camera.json (None: unreadable)
    gt_counts: dict[int, Counter] | None  # im_id -> Counter(obj_id) of GT instances (None: no GT)


def _list_images(folder: Path) -> dict[int, Path]:
    return {int(p.stem): p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.stem.isdigit()}


def _check_scene_files(scene_dir: Path, obj_ids: set[int] | None, out: _Collector) -> tuple[dict | None, dict | None]:
    """Parse the three scene files, check ids across them; return (cameras, gts)."""
    paths = {f: scene_dir / f for f in SCENE_FILES}
    cams = out.load(io.load_scene_camera, paths["scene_camera.json"])
    if cams is not None and (scene_dir / "depth").is_dir():
        raw = io.load_json(paths["scene_camera.json"])
        if no_scale := sorted(int(k) for k, d in raw.items() if "depth_scale" not in d):
            out.warning(paths["scene_camera.json"], "depth_scale", (
                f"missing for image ids {_short(no_scale)} although depth images exist: 1.0 assumed (depth PNG value "
                "= mm); the BOP toolkit needs it"))
    gts = infos = None
    if not paths["scene_gt.json"].is_file() and not paths["scene_gt_info.json"].is_file():
        out.warning(scene_dir, "scene_gt.json", "no scene_gt.json nor scene_gt_info.json (GT withheld?): GT checks skipped")
    else:
        gts = out.load(io.load_scene_gt, paths["scene_gt.json"])
        infos = out.load(io.load_scene_gt_info, paths["scene_gt_info.json"])
    loaded = {f: d for f, d in zip(SCENE_FILES, (cams, gts, infos)) if d is not None}
    for f, d in loaded.items():
        for g, other in loaded.items():
            if missing := sorted(set(other) - set(d)):
                out.error(paths[f], "image ids", f"image ids {_short(missing)} of {g} are missing here")
    if gts is not None and obj_ids is not None:
        for im_id, lst in gts.items():
            for i, g in enumerate(lst):
                if g.obj_id not in obj_ids:
                    out.error(paths["scene_gt.json"], f"{im_id}[{i}].obj_id",
                              f"obj_id {g.obj_id} is not in models_info (known: {sorted(obj_ids)})")
    if gts is not None and infos is not None:
        for im_id in sorted(set(gts) & set(infos)):
            if len(gts[im_id]) != len(infos[im_id]):
                out.error(paths["scene_gt_info.json"], str(im_id),
                          f"{len(infos[im_id])} entries, but scene_gt.json has {len(gts[im_id])} GT instances for this image")
    return cams, gts


def _check_scene_images(
    scene_dir: Path, im_ids: list[int], cams: dict | None, gts: dict | None,
    sp: SplitParams | None, label: str, check_images: bool, out: _Collector,
) -> None:
    color = "gray" if sp is not None and sp.gray else "rgb"
    if not (scene_dir / color).is_dir() and (scene_dir / ("rgb" if color == "gray" else "gray")).is_dir():
        color = "rgb" if color == "gray" else "gray"
    found: dict[str, dict[int, Path]] = {}
    for sub, ext in ((color, sp.rgb_ext if sp else ".png"), ("depth", sp.depth_ext if sp else ".png")):
        folder = scene_dir / sub
        if not folder.is_dir():
            out.error(folder, sub, f"folder not found ({len(im_ids)} images listed in scene_camera.json)")
            found[sub] = {}
            continue
        found[sub] = _list_images(folder)
        for im_id in im_ids:
            if im_id not in found[sub]:
                out.error(folder / f"{im_id:06d}{ext}", sub, f"{sub} image of image id {im_id} not found")
    for sub in MASK_DIRS:
        folder = scene_dir / sub
        if gts is None or not folder.is_dir():
            continue
        names = {p.name for p in folder.iterdir()}
        for im_id in sorted(gts):
            for i in range(len(gts[im_id])):
                if (name := f"{im_id:06d}_{i:06d}.png") not in names:
                    out.error(folder / name, sub, f"{sub} of GT instance {i} of image {im_id} not found")
    if not check_images:
        return
    expected = sp.im_size if sp is not None else None
    for im_id in im_ids:
        sizes = {}
        for sub in (color, "depth"):
            if (p := found[sub].get(im_id)) is None or (header := out.load(io.image_header, p)) is None:
                continue
            size, mode = header
            if sub == "depth" and mode not in DEPTH_MODES:
                out.error(p, "bit depth", f"PIL mode {mode!r}: expected a single-channel 16-bit depth image "
                          "(BOP depth is uint16, value * depth_scale = mm); an 8-bit image loses the depth")
                continue
            sizes[sub] = (p, size)
            if expected is not None and size != expected:
                out.error(p, "size", f"{size[0]}x{size[1]} pixels, expected {expected[0]}x{expected[1]} (im_size of {label})")
        if expected is None and len(sizes) == 2 and sizes[color][1] != sizes["depth"][1]:
            (w, h), (wd, hd) = sizes[color][1], sizes["depth"][1]
            out.error(sizes["depth"][0], "size", f"{wd}x{hd} pixels, but the {color} image is {w}x{h}")
        if sizes and cams is not None and im_id in cams:
            p, (w, h) = next(iter(sizes.values()))
            w, h = expected or (w, h)  # a wrongly sized image is reported above, not here again
            cx, cy = float(cams[im_id].K[0, 2]), float(cams[im_id].K[1, 2])
            if not (0 <= cx <= w and 0 <= cy <= h):
                out.error(scene_dir / "scene_camera.json", f"{im_id}.cam_K",
                          f"principal point ({cx:.1f}, {cy:.1f}) lies outside the {w}x{h} image {p}")


def _check_scene(
    scene_dir: Path, sp: SplitParams | None, label: str, obj_ids: set[int] | None, check_images: bool, out: _Collector,
) -> _SceneIndex:
    cams, gts = _check_scene_files(scene_dir, obj_ids, out)
    im_ids = sorted(cams) if cams is not None else sorted(gts or {})
    _check_scene_images(scene_dir, im_ids, cams, gts, sp, label, check_images, out)
    counts = {im: Counter(g.obj_id for g in lst) for im, lst in gts.items()} if gts is not None else None
    return _SceneIndex(set(cams) if cams is not None else None, counts)


def _scene_dirs(split_dir: Path) -> list[Path]:
    return sorted(p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit())


def _index_split_quietly(split_dir: Path) -> dict[int, _SceneIndex]:
    """Scene index of a split that was not checked (its own problems are not reported)."""
    quiet = _Collector()
    index = {}
    for d in _scene_dirs(split_dir):
        cams = quiet.load(io.load_scene_camera, d / "scene_camera.json")
        gts = quiet.load(io.load_scene_gt, d / "scene_gt.json") if (d / "scene_gt.json").is_file() else None
        counts = {im: Counter(g.obj_id for g in lst) for im, lst in gts.items()} if gts is not None else None
        index[int(d.name)] = _SceneIndex(set(cams) if cams is not None else None, counts)
    return index


def split_folders(root: Path) -> list[str]:
    """Image split folders of a dataset: every folder except ``models*`` and hidden ones."""
    return sorted(p.name for p in Path(root).iterdir() if p.is_dir() and not p.name.startswith(("models", ".")))


def _test_split(root: Path, params: DatasetParams | None) -> str:
    if params is not None:
        return params.test_split
    tests = [s for s in split_folders(root) if s.startswith("test")]
    return "test" if "test" in tests or len(tests) != 1 else tests[0]


def _check_targets(
    root: Path, params: DatasetParams | None, obj_ids: set[int] | None,
    index: dict[str, dict[int, _SceneIndex]], out: _Collector,
) -> None:
    path = root / TARGETS_FILE
    if not path.is_file():
        return
    targets = out.load(io.load_test_targets, path)
    if targets is None:
        return
    split = _test_split(root, params)
    split_dir = root / split
    if split in index:
        scenes = index[split]
    elif split_dir.is_dir():
        scenes = _index_split_quietly(split_dir)
    else:
        out.error(path, "", f"the test split folder {split_dir} the targets refer to does not exist")
        scenes = None
    seen: dict[tuple[int, int, int], int] = {}
    for i, t in enumerate(targets):
        if obj_ids is not None and t.obj_id not in obj_ids:
            out.error(path, f"[{i}].obj_id", f"obj_id {t.obj_id} is not in models_info (known: {sorted(obj_ids)})")
        if (j := seen.setdefault((t.scene_id, t.im_id, t.obj_id), i)) != i:
            out.warning(path, f"[{i}]", f"same scene_id/im_id/obj_id as target [{j}]")
        if t.inst_count < 1:
            out.warning(path, f"[{i}].inst_count", "0 instances: a target with nothing to find")
        if scenes is None:
            continue
        scene_dir = split_dir / f"{t.scene_id:06d}"
        if (sc := scenes.get(t.scene_id)) is None:
            out.error(path, f"[{i}].scene_id", f"scene {t.scene_id} not found: no folder {scene_dir}")
            continue
        if sc.im_ids is not None and t.im_id not in sc.im_ids:
            out.error(path, f"[{i}].im_id", f"image {t.im_id} not in {scene_dir / 'scene_camera.json'}")
            continue
        if sc.gt_counts is not None and t.im_id in sc.gt_counts and (obj_ids is None or t.obj_id in obj_ids):
            n = sc.gt_counts[t.im_id][t.obj_id]
            if t.inst_count > n:
                out.error(path, f"[{i}].inst_count", (
                    f"{t.inst_count} instances of obj_id {t.obj_id}, but {scene_dir / 'scene_gt.json'} "
                    f"has {n} in image {t.im_id}"
                ))


def _check_image_targets(root: Path, params: DatasetParams | None, index: dict[str, dict[int, _SceneIndex]],
                         out: _Collector) -> None:
    """``test_targets_bop24.json`` (6D detection), if present: every entry an image of the test split, no repeats."""
    path = root / TARGETS_BOP24_FILE
    if not path.is_file():
        return
    targets = out.load(io.load_image_targets, path)
    if targets is None:
        return
    split = _test_split(root, params)
    split_dir = root / split
    scenes = index[split] if split in index else _index_split_quietly(split_dir) if split_dir.is_dir() else None
    if scenes is None:
        out.error(path, "", f"the test split folder {split_dir} the targets refer to does not exist")
        return
    seen: dict[tuple[int, int], int] = {}
    for i, t in enumerate(targets):
        if (j := seen.setdefault((t.scene_id, t.im_id), i)) != i:
            out.warning(path, f"[{i}]", f"same scene_id/im_id as target [{j}] (the toolkit keeps one)")
        scene_dir = split_dir / f"{t.scene_id:06d}"
        if (sc := scenes.get(t.scene_id)) is None:
            out.error(path, f"[{i}].scene_id", f"scene {t.scene_id} not found: no folder {scene_dir}")
        elif sc.im_ids is not None and t.im_id not in sc.im_ids:
            out.error(path, f"[{i}].im_id", f"image {t.im_id} not in {scene_dir / 'scene_camera.json'}")


def check_dataset(
    root: str | Path, name: str | None = None, splits: list[str] | None = None, check_images: bool = True,
    model_dirs: tuple[str, ...] = MODEL_DIRS,
) -> list[Problem]:
    """Check a BOP dataset folder: models, every scene of every split, test targets.

    Args:
        root: the dataset folder (contains ``models/``).
        name: key into the dataset parameter table (image sizes, obj ids); default: folder name.
        splits: split folders to check; default: every folder except ``models*``.
        check_images: read image headers (sizes vs params, rgb vs depth, principal point inside).
        model_dirs: the model folders whose meshes are read and checked (``models_info.json`` always is).
    """
    from tqdm import tqdm

    root = Path(root)
    out = _Collector()
    if not name and root.name in RENAMED_DATASETS:  # reported here, not as a Python warning
        out.warning(root, "name", renamed_dataset_message(root.name, root) + f"; read as {RENAMED_DATASETS[root.name]!r}")
    name = dataset_name_of(root, name, warn=False)
    params = DATASETS.get(name)
    if not root.is_dir():
        out.error(root, "", "dataset folder not found")
        return out.items
    if params is None:
        out.warning(root, "name", f"dataset {name!r} is not in the parameter table ({sorted(DATASETS)}): "
                    "image sizes only checked against each other")
    obj_ids = _check_models(root, params, out, model_dirs)
    present = split_folders(root)
    if not present and not splits:
        out.warning(root, "", "no split folders (e.g. train_pbr/, test/)")
    index: dict[str, dict[int, _SceneIndex]] = {}
    for split in splits or present:
        split_dir = root / split
        if not split_dir.is_dir():
            out.error(split_dir, "", f"split folder not found (present: {present})")
            continue
        sp = params.splits.get(split) if params is not None else None
        if params is not None and sp is None:
            out.warning(split_dir, "", f"split {split!r} is not in the parameter table of {name} {sorted(params.splits)}")
        scene_dirs = _scene_dirs(split_dir)
        if not scene_dirs:
            out.error(split_dir, "", "no scene folders (expected 6-digit scene ids, e.g. 000000/)")
        index[split] = {
            int(d.name): _check_scene(d, sp, f"{name}/{split}", obj_ids, check_images, out)
            for d in tqdm(scene_dirs, desc=f"check {split}", unit="scene", disable=None)
        }
    _check_targets(root, params, obj_ids, index, out)
    _check_image_targets(root, params, index, out)
    return out.items


# ----------------------------------------------------------------------------- results


def resolve_split_folder(root: Path, split: str, params: DatasetParams | None) -> Path | None:
    """Folder of a results file's split: ``test`` -> ``test_primesense`` etc. (as the toolkit's split_type)."""
    candidates = [split, split.replace("-", "_")]
    if params is not None and params.test_split.startswith(split + "_"):
        candidates.append(params.test_split)
    if root.is_dir():
        prefixed = [s for s in split_folders(root) if s.startswith(split + "_")]
        candidates += prefixed if len(prefixed) == 1 else []
    return next((root / c for c in candidates if (root / c).is_dir()), None)


def _check_result_ids(
    csv_path: Path, root: Path, name: str, split: str | None, rows: list[ResultRow], out: _Collector,
    allow_unknown_objects: bool = False,
) -> None:
    if not root.is_dir():
        out.error(root, "", "dataset folder not found")
        return
    info_path = root / "models" / "models_info.json"
    infos = out.load(io.load_models_info, info_path)
    split_dir = resolve_split_folder(root, split, DATASETS.get(name)) if split else None
    if split and split_dir is None:
        out.warning(csv_path, "file name", f"no folder for split {split!r} in {root}: scene/image ids not checked")
    quiet = _Collector()
    scene_ims: dict[int, set[int] | None] = {}
    reported: set[tuple] = set()
    unknown: Counter[int] = Counter()
    for row in rows:
        e, n = row.estimate, row.line
        assert e is not None  # check_results passes only rows with an estimate
        if infos is not None and e.obj_id not in infos:
            unknown[e.obj_id] += 1
            if not allow_unknown_objects and ("obj", e.obj_id) not in reported:
                reported.add(("obj", e.obj_id))
                out.error(csv_path, f"line {n}: obj_id",
                          f"obj_id {e.obj_id} is not in {info_path} (known: {sorted(infos)})")
        if split_dir is None:
            continue
        scene_dir = split_dir / f"{e.scene_id:06d}"
        if e.scene_id not in scene_ims:
            exists = scene_dir.is_dir()
            cams = quiet.load(io.load_scene_camera, scene_dir / "scene_camera.json") if exists else None
            scene_ims[e.scene_id] = set(cams) if cams is not None else None
            if not exists:
                out.error(csv_path, f"line {n}: scene_id", f"scene {e.scene_id} not found: no folder {scene_dir}")
        ims = scene_ims[e.scene_id]
        if ims is not None and e.im_id not in ims and (e.scene_id, e.im_id) not in reported:
            reported.add((e.scene_id, e.im_id))
            out.error(csv_path, f"line {n}: im_id", f"image {e.im_id} not in {scene_dir / 'scene_camera.json'}")
    out.items += [Problem(p.path, p.field, f"{p.message} (image ids of this scene not checked)", "warning")
                  for p in quiet.items]
    if allow_unknown_objects and unknown:
        out.warning(csv_path, "obj_id", f"obj_ids {_short(sorted(unknown))} are not in {info_path} "
                    f"({sum(unknown.values())} estimates): scored as the BOP toolkit scores them (they take "
                    "places among an image's best estimates and match no GT)")


def check_results(
    csv_path: str | Path, dataset_root: str | Path | None = None, name: str | None = None, split: str | None = None,
    allow_unknown_objects: bool = False,
) -> list[Problem]:
    """Check a BOP19 results CSV: file name, header, every row, units, time rule, ids in the dataset.

    Args:
        csv_path: the ``METHOD_DATASET-SPLIT.csv`` file.
        dataset_root: dataset folder to check scene/image/object ids against (None: format only).
        name: dataset name the file must be for (default: as in the file name; compared with the
            folder name as a warning).
        split: split the file must be for (default: as in the file name).
        allow_unknown_objects: object ids the dataset lacks are one warning, not an error (the 6D
            detection task, which the toolkit scores with them).
    """
    path = Path(csv_path)
    out = _Collector()
    file_dataset: str | None
    file_split: str | None
    try:
        _, file_dataset, file_split = parse_results_filename(path)
    except BopFormatError as e:
        out.items.append(Problem.from_error(e))
        file_dataset = file_split = None
    given = [n for n in (name, dataset_name_of(dataset_root) if dataset_root is not None else None) if n]
    if file_dataset is not None and (why := misread_dataset(path, given)) is not None:
        out.error(path, "file name", why)
        file_dataset = file_split = None  # what the toolkit reads is not what the file is for
    if name and ("-" in name or "_" in name):
        out.error(path, "file name", f"dataset name {name!r} contains '-' or '_': the BOP toolkit cannot read "
                  "results file names METHOD_DATASET-SPLIT.csv of such a dataset")
    if file_dataset is not None and name and name != file_dataset:
        out.error(path, "file name", f"results for dataset {file_dataset!r}, expected {name!r}")
    if file_split is not None and split and split != file_split:
        out.error(path, "file name", f"results for split {file_split!r}, expected {split!r}")
    root = Path(dataset_root) if dataset_root is not None else None
    if root is not None and not name:
        folder_name = dataset_name_of(root)
        name = file_dataset or folder_name
        if file_dataset is not None and file_dataset != folder_name:
            out.warning(path, "file name", f"dataset {file_dataset!r} of the file name differs from the folder name of {root}")

    rows = []
    try:
        for row in parse_results_csv(path):
            out.items += [Problem.from_error(e) for e in row.problems]
            if row.estimate is not None:
                rows.append(row)
    except BopFormatError as e:
        out.items.append(Problem.from_error(e))
        return out.items
    if not rows and not any(p.severity == "error" for p in out.items):
        out.warning(path, "", "no pose estimates in the file")
    raw = path.read_bytes()
    if raw.startswith(codecs.BOM_UTF8):
        out.warning(path, "line 1: header", "starts with a UTF-8 byte-order mark (read as the BOP toolkit does: "
                    "ignored; it writes none)")
    if raw.endswith(b"\n") and not raw.endswith((b"\n\n", b"\n\r\n")):
        n_lines = raw.count(b"\n")
        out.warning(path, f"line {n_lines}: row", "newline after the last line (the BOP toolkit writes none)")
    first: dict[str, int] = {}
    for row in rows:
        assert row.estimate is not None  # rows keeps only the rows with an estimate
        if (n0 := first.setdefault(format_estimate(row.estimate), row.line)) != row.line:
            out.warning(path, f"line {row.line}: row", f"identical to line {n0}")
    if root is not None:
        _check_result_ids(path, root, name or dataset_name_of(root), split or file_split, rows, out,
                          allow_unknown_objects)
    return out.items

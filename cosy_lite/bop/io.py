"""Read and write BOP files. Millimetres on disk, metres in every value handed out.

Every reader checks what it reads and raises :class:`~cosy_lite.errors.BopFormatError` naming the
file and the field. Layout and field names follow the BOP format documentation
(``docs/bop_datasets_format.md`` of the BOP toolkit).
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import cv2
import numpy as np

from cosy_lite.errors import BopFormatError

if TYPE_CHECKING:
    import trimesh

MM = 1e-3  # metres per millimetre
MM_PER_M = 1000.0  # multiply (not divide by MM) so 0.3 m is written as 300.0
MIN_PLAUSIBLE_T_MM = 20.0  # a cam_t_m2c shorter than this is almost surely in metres
MIN_PLAUSIBLE_DIAMETER_MM = 5.0  # a model smaller than this is almost surely in metres
NO_MESH = "no vertices with faces (an empty mesh or a point cloud); BOP models are triangle meshes"
# The most pixels (width x height) of any image read (colour, depth, mask): 40 MP, above an 8K frame
# (7680x4320 = 33 MP), far above any BOP dataset's. Checked from the file's header before anything
# is decoded, so a small file that claims a huge image never reaches a large allocation.
MAX_IMAGE_PIXELS = 40_000_000
_PIL_LIMIT = threading.Lock()  # guards PIL's global limit while image_header lifts it


# ----------------------------------------------------------------------------- records


@dataclass
class ModelInfo:
    """One entry of ``models_info.json``, in metres."""

    obj_id: int
    diameter: float  # largest distance between two vertices [m]
    mins: np.ndarray  # [3] min_x, min_y, min_z [m]
    sizes: np.ndarray  # [3] size_x, size_y, size_z [m]
    symmetries_discrete: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # [S,4,4], t in m
    symmetries_continuous: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (axis, offset [m])

    @property
    def is_symmetric(self) -> bool:
        return len(self.symmetries_discrete) > 0 or len(self.symmetries_continuous) > 0


@dataclass
class CameraRecord:
    """One entry of ``scene_camera.json``."""

    K: np.ndarray  # [3,3]
    depth_scale: float = 1.0  # depth PNG value * depth_scale = millimetres
    T_CW: np.ndarray | None = None  # [4,4] world-to-camera [m], if given


@dataclass
class GtPose:
    """One entry of ``scene_gt.json``: an object instance and its pose."""

    obj_id: int
    TCO: np.ndarray  # [4,4] object-to-camera [m]


@dataclass
class GtInfo:
    """One entry of ``scene_gt_info.json`` (pixel boxes are [x, y, w, h])."""

    bbox_obj: list[int]
    bbox_visib: list[int]
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float


@dataclass(frozen=True)
class Target:
    """One entry of ``test_targets_bop19.json``."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


@dataclass(frozen=True)
class ImageTarget:
    """One entry of ``test_targets_bop24.json`` (6D detection: an image, no object or instance count)."""

    scene_id: int
    im_id: int


# ----------------------------------------------------------------------------- json helpers


def load_json(path: str | Path) -> Any:
    """Load a JSON file; missing or malformed files raise BopFormatError."""
    path = Path(path)
    if not path.is_file():
        raise BopFormatError(path, "", "file not found")
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise BopFormatError(path, "", f"malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    except UnicodeDecodeError as e:
        raise BopFormatError(path, "", f"not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    except RecursionError:
        raise BopFormatError(path, "", "JSON nested too deeply") from None


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write a text file atomically (temp file + rename), creating parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def _fmt(x: Any) -> str:
    if isinstance(x, (float, np.floating)):
        return repr(float(x))
    if isinstance(x, (np.integer,)):
        return str(int(x))
    return json.dumps(x)


def dumps_bop(obj: Any) -> str:
    """JSON in the BOP toolkit style: one top-level key per line, lists of numbers on one line."""

    def enc(o: Any, indent: int) -> str:
        pad = "  " * indent
        if isinstance(o, dict):
            if not o:
                return "{}"
            items = [f'{pad}  {json.dumps(str(k))}: {enc(v, indent + 1)}' for k, v in o.items()]
            return "{\n" + ",\n".join(items) + "\n" + pad + "}"
        if isinstance(o, (list, tuple)):
            if all(not isinstance(v, (dict, list, tuple)) for v in o):
                return "[" + ", ".join(_fmt(v) for v in o) + "]"
            items = [f"{pad}  {enc(v, indent + 1)}" for v in o]
            return "[\n" + ",\n".join(items) + "\n" + pad + "]"
        return _fmt(o)

    return enc(obj, 0) + "\n"


def save_json(path: str | Path, obj: Any) -> None:
    atomic_write_text(path, dumps_bop(obj))


def _im_key(path: Path, key: str) -> int:
    if not (key.isascii() and key.isdigit()):  # int() would also take " 1", "+1" and "1_0"
        raise BopFormatError(path, key, "keys must be non-negative integer ids written as strings, e.g. \"0\"")
    return int(key)


def _flat_numbers(value: Any) -> list[float] | None:
    """The JSON numbers of ``value`` (a number or nested lists, as numpy reads them), None if
    anything else is in it (strings and booleans are not numbers)."""
    if isinstance(value, list):
        out: list[float] = []
        for v in value:
            if (sub := _flat_numbers(v)) is None:
                return None
            out += sub
        return out
    return [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _numbers(path: Path, fld: str, value: Any, n: int) -> np.ndarray:
    """``n`` JSON numbers (a number or a list, possibly nested: ``cam_K`` as 3 rows); anything else raises."""
    items = _flat_numbers(value)
    expected = f"expected {n} number{'s' if n != 1 else ''}"
    if items is None:
        raise BopFormatError(path, fld, f"{expected}, got {value!r}")
    arr = np.asarray(items, dtype=np.float64)
    if arr.size != n:
        raise BopFormatError(path, fld, f"{expected}, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise BopFormatError(path, fld, f"contains NaN or inf: {arr.tolist()}")
    return arr


def _integers(path: Path, fld: str, value: Any, n: int) -> list[int]:
    """``n`` integers (written as JSON integers or integral floats); anything else raises."""
    if type(value) is int and n == 1:  # JSON integers, the usual case: nothing to convert or check
        return [value]
    if type(value) is list and len(value) == n and all(type(v) is int for v in value):
        return list(value)
    arr = _numbers(path, fld, value, n)
    if not np.all(arr == np.round(arr)):
        raise BopFormatError(path, fld, f"expected {n} integers, got {arr.tolist()}")
    return [int(v) for v in arr]


def _get(path: Path, d: Any, fld: str, where: str) -> Any:
    if not isinstance(d, dict) or fld not in d:
        raise BopFormatError(path, f"{where}.{fld}" if where else fld, "missing field")
    return d[fld]


def _check_rotation(path: Path, fld: str, R: np.ndarray) -> None:
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > 1e-3 or np.linalg.det(R) < 0:
        raise BopFormatError(path, fld, f"not a rotation matrix (|R R^T - I| = {err:.2g}, det = {np.linalg.det(R):.3f})")


def _check_obj_id(path: Path, fld: str, obj_id: Any, valid_ids: set[int] | None) -> int:
    if not isinstance(obj_id, (int, np.integer)) or isinstance(obj_id, bool):
        raise BopFormatError(path, fld, f"obj_id must be an integer, got {obj_id!r}")
    if valid_ids is not None and int(obj_id) not in valid_ids:
        raise BopFormatError(path, fld, f"obj_id {obj_id} is not in models_info (known: {sorted(valid_ids)})")
    return int(obj_id)


# ----------------------------------------------------------------------------- models


def load_models_info(path: str | Path) -> dict[int, ModelInfo]:
    """``models_info.json`` -> {obj_id: ModelInfo} in metres."""
    path = Path(path)
    raw = load_json(path)
    if not isinstance(raw, dict) or not raw:
        raise BopFormatError(path, "", "expected a non-empty JSON object keyed by obj_id")
    out = {}
    for key, d in raw.items():
        obj_id = _im_key(path, key)
        diameter = float(_numbers(path, f"{key}.diameter", _get(path, d, "diameter", key), 1)[0])
        if diameter < MIN_PLAUSIBLE_DIAMETER_MM:
            raise BopFormatError(
                path, f"{key}.diameter",
                f"{diameter} is implausibly small for millimetres (models in metres? BOP uses mm)",
            )
        mins = np.array([float(_numbers(path, f"{key}.min_{a}", _get(path, d, f"min_{a}", key), 1)[0]) for a in "xyz"])
        sizes = np.array([float(_numbers(path, f"{key}.size_{a}", _get(path, d, f"size_{a}", key), 1)[0]) for a in "xyz"])
        syms_d = []
        for i, s in enumerate(d.get("symmetries_discrete", [])):
            fld = f"{key}.symmetries_discrete[{i}]"
            S = _numbers(path, fld, s, 16).reshape(4, 4)
            _check_rotation(path, fld, S[:3, :3])
            S[:3, 3] *= MM
            syms_d.append(S)
        syms_c = []
        for i, s in enumerate(d.get("symmetries_continuous", [])):
            fld = f"{key}.symmetries_continuous[{i}]"
            axis = _numbers(path, fld + ".axis", _get(path, s, "axis", fld), 3)
            if np.linalg.norm(axis) < 1e-6:
                raise BopFormatError(path, fld + ".axis", "axis must be non-zero")
            offset = _numbers(path, fld + ".offset", _get(path, s, "offset", fld), 3) * MM
            syms_c.append((axis / np.linalg.norm(axis), offset))
        out[obj_id] = ModelInfo(
            obj_id, diameter * MM, mins * MM, sizes * MM,
            np.array(syms_d).reshape(-1, 4, 4), syms_c,
        )
    return out


def models_info_to_json(infos: dict[int, ModelInfo]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for obj_id in sorted(infos):
        m = infos[obj_id]
        d: dict[str, Any] = {"diameter": float(m.diameter * MM_PER_M)}
        for i, a in enumerate("xyz"):
            d[f"min_{a}"] = float(m.mins[i] * MM_PER_M)
        for i, a in enumerate("xyz"):
            d[f"size_{a}"] = float(m.sizes[i] * MM_PER_M)
        if len(m.symmetries_discrete):
            syms = []
            for S in m.symmetries_discrete:
                S = np.array(S, dtype=np.float64)
                S[:3, 3] *= MM_PER_M
                syms.append([float(v) for v in S.reshape(-1)])
            d["symmetries_discrete"] = syms
        if m.symmetries_continuous:
            d["symmetries_continuous"] = [
                {"axis": [float(v) for v in axis], "offset": [float(v * MM_PER_M) for v in offset]}
                for axis, offset in m.symmetries_continuous
            ]
        out[str(obj_id)] = d
    return out


def save_models_info(path: str | Path, infos: dict[int, ModelInfo]) -> None:
    save_json(path, models_info_to_json(infos))


def faces_problem(faces: np.ndarray, n_vertices: int) -> str | None:
    """Why ``faces [F,3]`` (vertex indices) do not make a mesh of ``n_vertices`` vertices, or None."""
    if faces.ndim != 2 or len(faces) == 0:
        return "mesh has no faces (BOP models are triangle meshes)"
    if faces.min() < 0 or faces.max() >= n_vertices:
        return f"face vertex indices span {int(faces.min())}..{int(faces.max())}, expected 0..{n_vertices - 1}"
    return None


def load_model(path: str | Path) -> trimesh.Trimesh:
    """Load a BOP model (PLY in mm, optional texture) as a ``trimesh.Trimesh`` in metres."""
    path = Path(path)
    mesh = _trimesh_model(path)
    _check_model(path, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    mesh.apply_scale(MM)
    return mesh


def load_model_geometry(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The geometry of a BOP model: (vertices [N,3] float64 in metres, faces [F,3] int64), the
    arrays of :func:`load_model`, with its checks."""
    path = Path(path)
    vertices, faces = read_model_arrays(path)
    _check_model(path, vertices, faces)
    return vertices * MM, faces


def read_model_arrays(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [N,3] float64 in the file's units, faces [F,3] int64) of a PLY model, unchecked;
    read without trimesh where the file allows (:func:`cosy_lite.bop.ply.read_triangles`: binary
    triangle meshes, as BOP's), else by trimesh."""
    from cosy_lite.bop.ply import read_triangles

    path = Path(path)
    if not path.is_file():
        raise BopFormatError(path, "", "model file not found")
    arrays = read_triangles(path)
    if arrays is None:
        mesh = _trimesh_model(path)
        faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
        arrays = np.asarray(mesh.vertices, dtype=np.float64), faces
    return arrays


def _trimesh_model(path: Path) -> trimesh.Trimesh:
    import trimesh

    if not path.is_file():
        raise BopFormatError(path, "", "model file not found")
    try:
        # force="mesh" returns a Trimesh (a scene's geometries concatenated); trimesh types it as Geometry
        return cast(trimesh.Trimesh, trimesh.load(path, force="mesh", process=False))
    except Exception as e:  # trimesh raises many types on bad files
        raise BopFormatError(path, "", f"cannot read mesh ({type(e).__name__}: {e})") from None


def _check_model(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Raise BopFormatError if the model's vertices (mm) and faces are not a plausible BOP mesh."""
    if len(vertices) == 0:
        raise BopFormatError(path, "vertex", NO_MESH)
    if not np.all(np.isfinite(vertices)):
        raise BopFormatError(path, "vertex", "vertices contain NaN or inf")
    if (msg := faces_problem(faces, len(vertices))) is not None:
        raise BopFormatError(path, "face", msg)
    extent = float(np.ptp(vertices, axis=0).max())
    if extent < MIN_PLAUSIBLE_DIAMETER_MM:
        raise BopFormatError(path, "vertex", f"model extent {extent:.4g} is implausibly small for mm (model in metres?)")


# ----------------------------------------------------------------------------- scene files


def load_scene_camera(path: str | Path) -> dict[int, CameraRecord]:
    path = Path(path)
    raw = load_json(path)
    if not isinstance(raw, dict):
        raise BopFormatError(path, "", "expected a JSON object keyed by image id")
    out = {}
    for key, d in raw.items():
        im_id = _im_key(path, key)
        K = _numbers(path, f"{key}.cam_K", _get(path, d, "cam_K", key), 9).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1) > 1e-6:
            raise BopFormatError(
                path, f"{key}.cam_K", f"not an intrinsic matrix (row-major, fx, fy > 0, K[2,2] = 1): {K.reshape(-1).tolist()}"
            )
        depth_scale = float(_numbers(path, f"{key}.depth_scale", d.get("depth_scale", 1.0), 1)[0])
        if depth_scale <= 0:
            raise BopFormatError(path, f"{key}.depth_scale", f"must be > 0, got {depth_scale}")
        T_CW = None
        if "cam_R_w2c" in d or "cam_t_w2c" in d:
            R = _numbers(path, f"{key}.cam_R_w2c", _get(path, d, "cam_R_w2c", key), 9).reshape(3, 3)
            _check_rotation(path, f"{key}.cam_R_w2c", R)
            t = _numbers(path, f"{key}.cam_t_w2c", _get(path, d, "cam_t_w2c", key), 3) * MM
            T_CW = np.eye(4)
            T_CW[:3, :3], T_CW[:3, 3] = R, t
        out[im_id] = CameraRecord(K, depth_scale, T_CW)
    return out


@dataclass
class CameraFile:
    """Intrinsics of one camera read by :func:`load_camera_file`."""

    K: np.ndarray  # [3,3] px
    size: tuple[int, int] | None = None  # (width, height) px, if the file states it
    depth_scale: float | None = None  # depth image value * depth_scale = mm, if the file states it


def load_camera_file(path: str | Path) -> CameraFile:
    """One camera's intrinsics from JSON: a BOP ``camera.json`` (``fx, fy, cx, cy`` [, ``width, height,
    depth_scale``]), a ``scene_camera.json`` entry (``cam_K`` row-major [, ``depth_scale``]) or ``{"K":
    [[..], [..], [..]]}``. Anything else raises BopFormatError naming the file and field."""
    path = Path(path)
    d = load_json(path)
    if not isinstance(d, dict):
        raise BopFormatError(path, "", "expected a JSON object with fx, fy, cx, cy (BOP camera.json), cam_K or K")
    if "cam_K" in d or "K" in d:
        fld = "cam_K" if "cam_K" in d else "K"
        K = _numbers(path, fld, d[fld], 9).reshape(3, 3)
        if abs(K[2, 2] - 1) > 1e-6 or np.any(K[2, :2] != 0) or K[1, 0] != 0:
            raise BopFormatError(path, fld, f"not an intrinsic matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]: {K.tolist()}")
    else:
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in d]
        if missing:
            raise BopFormatError(path, missing[0], "missing field (expected fx, fy, cx, cy as in BOP camera.json, "
                                 "or cam_K / K)")
        fx, fy, cx, cy = (float(_numbers(path, k, d[k], 1)[0]) for k in ("fx", "fy", "cx", "cy"))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        fld = "fx"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise BopFormatError(path, fld, f"focal lengths must be > 0 px, got fx = {K[0, 0]}, fy = {K[1, 1]}")
    size = None
    if "width" in d or "height" in d:
        w, h = (_numbers(path, k, _get(path, d, k, ""), 1)[0] for k in ("width", "height"))
        if w <= 0 or h <= 0 or w != int(w) or h != int(h):
            raise BopFormatError(path, "width", f"image size must be positive integers, got {w} x {h}")
        size = (int(w), int(h))
    depth_scale = None
    if "depth_scale" in d:
        depth_scale = float(_numbers(path, "depth_scale", d["depth_scale"], 1)[0])
        if depth_scale <= 0:
            raise BopFormatError(path, "depth_scale", f"must be > 0 (depth value * depth_scale = mm), got {depth_scale}")
    return CameraFile(K, size, depth_scale)


def scene_camera_to_json(cams: dict[int, CameraRecord]) -> dict[str, Any]:
    out = {}
    for im_id in sorted(cams):
        c = cams[im_id]
        d: dict[str, Any] = {"cam_K": [float(v) for v in np.asarray(c.K).reshape(-1)], "depth_scale": float(c.depth_scale)}
        if c.T_CW is not None:
            d["cam_R_w2c"] = [float(v) for v in c.T_CW[:3, :3].reshape(-1)]
            d["cam_t_w2c"] = [float(v * MM_PER_M) for v in c.T_CW[:3, 3]]
        out[str(im_id)] = d
    return out


def _load_per_image_lists(path: Path, what: str, parse_entry) -> dict[int, list]:
    """A scene file keyed by image id whose values are lists; ``parse_entry(d, where)`` per entry."""
    raw = load_json(path)
    if not isinstance(raw, dict):
        raise BopFormatError(path, "", "expected a JSON object keyed by image id")
    out = {}
    for key, lst in raw.items():
        im_id = _im_key(path, key)
        if not isinstance(lst, list):
            raise BopFormatError(path, key, f"expected a list of {what}")
        out[im_id] = [parse_entry(d, f"{key}[{i}]") for i, d in enumerate(lst)]
    return out


def load_scene_gt(path: str | Path, valid_obj_ids: set[int] | None = None) -> dict[int, list[GtPose]]:
    path = Path(path)

    def parse(d: Any, where: str) -> GtPose:
        obj_id = _check_obj_id(path, f"{where}.obj_id", _get(path, d, "obj_id", where), valid_obj_ids)
        R = _numbers(path, f"{where}.cam_R_m2c", _get(path, d, "cam_R_m2c", where), 9).reshape(3, 3)
        _check_rotation(path, f"{where}.cam_R_m2c", R)
        t = _numbers(path, f"{where}.cam_t_m2c", _get(path, d, "cam_t_m2c", where), 3)
        if np.linalg.norm(t) < MIN_PLAUSIBLE_T_MM:
            raise BopFormatError(
                path, f"{where}.cam_t_m2c",
                f"{t.tolist()} is implausibly close for millimetres (metres? BOP uses mm)",
            )
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t * MM
        return GtPose(obj_id, T)

    return _load_per_image_lists(path, "GT instances", parse)


def scene_gt_to_json(gts: dict[int, list[GtPose]]) -> dict[str, Any]:
    return {
        str(im_id): [
            {
                "cam_R_m2c": [float(v) for v in g.TCO[:3, :3].reshape(-1)],
                "cam_t_m2c": [float(v * MM_PER_M) for v in g.TCO[:3, 3]],
                "obj_id": int(g.obj_id),
            }
            for g in gts[im_id]
        ]
        for im_id in sorted(gts)
    }


def load_scene_gt_info(path: str | Path) -> dict[int, list[GtInfo]]:
    path = Path(path)

    def parse(d: Any, where: str) -> GtInfo:
        vals: dict[str, Any] = {}
        for fld in ("bbox_obj", "bbox_visib"):
            vals[fld] = _integers(path, f"{where}.{fld}", _get(path, d, fld, where), 4)
        for fld in ("px_count_all", "px_count_valid", "px_count_visib"):
            vals[fld] = _integers(path, f"{where}.{fld}", _get(path, d, fld, where), 1)[0]
            if vals[fld] < 0:
                raise BopFormatError(path, f"{where}.{fld}", f"must be >= 0, got {vals[fld]}")
        vf = float(_numbers(path, f"{where}.visib_fract", _get(path, d, "visib_fract", where), 1)[0])
        if not 0.0 <= vf <= 1.0:
            raise BopFormatError(path, f"{where}.visib_fract", f"must be in [0, 1], got {vf}")
        return GtInfo(visib_fract=vf, **vals)

    return _load_per_image_lists(path, "GT info entries", parse)


def scene_gt_info_to_json(infos: dict[int, list[GtInfo]]) -> dict[str, Any]:
    return {
        str(im_id): [
            {
                "bbox_obj": [int(v) for v in g.bbox_obj],
                "bbox_visib": [int(v) for v in g.bbox_visib],
                "px_count_all": int(g.px_count_all),
                "px_count_valid": int(g.px_count_valid),
                "px_count_visib": int(g.px_count_visib),
                "visib_fract": float(g.visib_fract),
            }
            for g in infos[im_id]
        ]
        for im_id in sorted(infos)
    }


def load_test_targets(path: str | Path, valid_obj_ids: set[int] | None = None) -> list[Target]:
    path = Path(path)
    raw = load_json(path)
    if not isinstance(raw, list):
        raise BopFormatError(path, "", "expected a JSON list of {scene_id, im_id, obj_id, inst_count}")
    out = []
    for i, d in enumerate(raw):
        where = f"[{i}]"
        vals = {}
        for fld in ("scene_id", "im_id", "inst_count"):
            v = _get(path, d, fld, where)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise BopFormatError(path, f"{where}.{fld}", f"expected a non-negative integer, got {v!r}")
            vals[fld] = v
        vals["obj_id"] = _check_obj_id(path, f"{where}.obj_id", _get(path, d, "obj_id", where), valid_obj_ids)
        out.append(Target(**vals))
    return out


def load_image_targets(path: str | Path) -> list[ImageTarget]:
    """``test_targets_bop24.json``: a JSON list of ``{"im_id", "scene_id"}`` (other keys are ignored, as
    the toolkit does: e.g. a BOP19-style ``obj_id``/``inst_count``). Bad entries raise BopFormatError."""
    path = Path(path)
    raw = load_json(path)
    if not isinstance(raw, list):
        raise BopFormatError(path, "", "expected a JSON list of {im_id, scene_id}")
    out = []
    for i, d in enumerate(raw):
        vals = {}
        for fld in ("scene_id", "im_id"):
            v = _get(path, d, fld, f"[{i}]")
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise BopFormatError(path, f"[{i}].{fld}", f"expected a non-negative integer, got {v!r}")
            vals[fld] = v
        out.append(ImageTarget(**vals))
    return out


def image_targets_to_json(targets: list[ImageTarget]) -> list[dict[str, int]]:
    return [{"im_id": t.im_id, "scene_id": t.scene_id} for t in targets]


def targets_to_json(targets: list[Target]) -> list[dict[str, int]]:
    return [
        {"im_id": t.im_id, "inst_count": t.inst_count, "obj_id": t.obj_id, "scene_id": t.scene_id}
        for t in targets
    ]


# ----------------------------------------------------------------------------- images


def image_header(path: str | Path) -> tuple[tuple[int, int], str]:
    """((width, height), PIL mode) of an image file, from its header only (nothing is decoded).

    Raises BopFormatError naming the file when the header cannot be read, or when the image has
    more than :data:`MAX_IMAGE_PIXELS` pixels. Every reader of images here calls it first.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        # PIL refuses very large images itself (DecompressionBombError) without saying their size;
        # its limit is lifted for the header, ours below applies to every size
        with _PIL_LIMIT:
            pil_limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
            try:
                with Image.open(path) as im:
                    size, mode = (int(im.size[0]), int(im.size[1])), im.mode
            finally:
                Image.MAX_IMAGE_PIXELS = pil_limit
    except (OSError, UnidentifiedImageError, ValueError) as e:
        raise BopFormatError(path, "", f"cannot read the image header: {e}") from None
    if size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise BopFormatError(path, "size", f"{size[0]} x {size[1]} pixels ({size[0] * size[1] / 1e6:.0f} MP): more than "
                             f"the limit of {MAX_IMAGE_PIXELS / 1e6:.0f} MP (cosy_lite.bop.io.MAX_IMAGE_PIXELS = "
                             f"{MAX_IMAGE_PIXELS} pixels)")
    return size, mode


def load_image(path: str | Path) -> np.ndarray:
    """Colour image as RGB uint8 [H,W,3] (grayscale images are repeated to 3 channels)."""
    path = Path(path)
    if not path.is_file():
        raise BopFormatError(path, "", "image file not found")
    image_header(path)
    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if im is None:
        raise BopFormatError(path, "", "cannot decode image")
    if im.dtype == np.uint16:  # the same brightness for every image (a per-image min-max stretch would not be)
        im = np.round(im / 257.0).astype(np.uint8)
    elif im.dtype != np.uint8:
        raise BopFormatError(path, "bit depth", f"{im.dtype} pixels: expected an 8-bit (or 16-bit) colour image")
    if im.ndim == 2:
        return np.repeat(im[:, :, None], 3, axis=2)
    if im.shape[2] == 2:  # gray + alpha
        return np.repeat(im[:, :, :1], 3, axis=2)
    return cv2.cvtColor(im[:, :, :3], cv2.COLOR_BGR2RGB)


def save_image(path: str | Path, rgb: np.ndarray, jpeg_quality: int = 95) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if path.suffix.lower() in (".jpg", ".jpeg") else []
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params):
        raise OSError(f"{path}: cannot write image")


def load_depth(path: str | Path, depth_scale: float) -> np.ndarray:
    """Depth PNG/TIF -> float32 [H,W] in metres (0 = no measurement)."""
    path = Path(path)
    if not path.is_file():
        raise BopFormatError(path, "", "depth file not found")
    image_header(path)
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.ndim != 2:
        what = "cannot decode the image" if d is None else f"{d.shape[2]} channels"
        raise BopFormatError(path, "", f"{what}: expected a single-channel 16-bit depth image")
    if d.dtype != np.uint16:
        raise BopFormatError(path, "bit depth", f"{d.dtype} pixels: expected uint16 (BOP depth is 16-bit, "
                             "value * depth_scale = mm); an 8-bit image loses the depth")
    return np.multiply(d, np.float32(depth_scale * MM), dtype=np.float32)  # (one pass; uint16 -> float32 is exact)


def depth_to_png_units(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metres -> the uint16 values written to a depth PNG (value * depth_scale = mm)."""
    q = np.round(depth_m / (depth_scale * MM))
    if q.max(initial=0) > 65535:
        raise ValueError(f"depth {depth_m.max():.3f} m does not fit uint16 with depth_scale {depth_scale}")
    return q.astype(np.uint16)


def save_depth_png(path: str | Path, depth_png: np.ndarray) -> None:
    """Write already quantised uint16 depth values (see :func:`depth_to_png_units`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), depth_png):
        raise OSError(f"{path}: cannot write depth")


def save_depth(path: str | Path, depth_m: np.ndarray, depth_scale: float) -> None:
    save_depth_png(path, depth_to_png_units(depth_m, depth_scale))


def load_mask(path: str | Path) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise BopFormatError(path, "", "mask file not found")
    image_header(path)
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise BopFormatError(path, "", "cannot decode mask")
    return m > 127


def save_mask(path: str | Path, mask: np.ndarray) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), mask.astype(np.uint8) * 255)

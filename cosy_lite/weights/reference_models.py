"""Reference models: trained networks kept in the repository, one folder per dataset.

``models/NAME/`` of the repository (installed as the package data ``cosy_lite/reference/weights/NAME/``;
or ``$COSY_LITE_MODELS/NAME/``) holds, for the dataset
NAME (e.g. ``ycbvsynth``), each trained network as ``KIND.safetensors`` or, above
:data:`MAX_FILE_BYTES`, its shards ``KIND-0000i-of-0000N.safetensors`` (fp16 weights + the training
config and metadata as JSON, :func:`~cosy_lite.weights.checkpoint.save_weights`: loading runs no
code) with its card ``KIND.json`` (dataset, object ids, exact training command, steps, crops seen,
wall time, machine, held-out metrics; ``weights``: the files, ``files``: each one's size in bytes
and sha256), and ``pipeline.json``: how the set is meant to run (start poses, candidates, refiner
iterations) and what the whole pipeline measured on the dataset's test split.

Finding a set checks each card against the folder (:data:`CARD_FIELDS`, then every file the card
names present, no other file of that network, sizes and sha256 as written): a damaged, missing,
extra or replaced file is a :class:`ReferenceModelError` naming the card, the file and the field.
Each file is hashed once per process (cached by path, mtime and size; ~0.03 s for the 12.6 MB of
``ycbvsynth``).

:func:`reference_models` finds a set by name (``Predictor.from_pretrained(NAME)``, ``infer.py
--pretrained NAME``; :func:`fill_networks` completes a command line); :func:`publish` writes one network of
a set from a training run.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from cosy_lite.errors import CosyLiteError

KINDS = ("detector", "coarse", "refiner", "scorer")
PIPELINE_FILE = "pipeline.json"
_NAME = re.compile(r"^[A-Za-z0-9]+$")  # a BOP dataset name: no '_' or '-'


MAX_FILE_BYTES = 4 * 2**20  # larger weights are sharded: the repository keeps no file over 5 MB
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


def _count(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _file_entry(v: Any) -> bool:
    return isinstance(v, dict) and _count(v.get("bytes")) and bool(_SHA256.match(str(v.get("sha256"))))


def _id_list(v: Any) -> bool:
    from cosy_lite.weights.checkpoint import is_id_list

    return is_id_list(v)


# typed fields of a card KIND.json: name -> (check, what is expected, required)
CARD_FIELDS: dict[str, tuple[Callable[[Any], bool], str, bool]] = {
    "kind": (lambda v: v in KINDS, f"one of {list(KINDS)}", True),
    "weights": (lambda v: isinstance(v, list) and len(v) > 0 and all(isinstance(n, str) for n in v),
                "a list of the weights file names", True),
    "files": (lambda v: isinstance(v, dict) and all(_file_entry(e) for e in v.values()),
              "a JSON object: file name -> {'bytes': integer >= 0, 'sha256': 64 hex digits}", True),
    "weights_bytes": (_count, "an integer >= 0", False),
    "dataset": (lambda v: isinstance(v, str), "a dataset name (a string)", False),
    "obj_ids": (_id_list, "a list of positive integers", False),
    "steps": (_count, "an integer >= 0", False),
}


def reference_root() -> Path:
    """The folder of the sets: ``$COSY_LITE_MODELS``; else the installed package's data
    ``cosy_lite/reference/weights/`` (found with importlib.resources); else, in a source checkout,
    its top-level ``models/`` (the folder that data is installed from, see pyproject.toml)."""
    env = os.environ.get("COSY_LITE_MODELS")
    if env:
        return Path(env)
    from importlib.resources import files

    installed = Path(str(files("cosy_lite.reference").joinpath("weights")))
    return installed if installed.is_dir() else Path(__file__).resolve().parents[2] / "models"


def weights_file(folder: Path, kind: str) -> Path | None:
    """``KIND.safetensors`` of ``folder``, or the first of its shards; None if it has neither."""
    single = folder / f"{kind}.safetensors"
    if single.is_file():
        return single
    first = sorted(folder.glob(f"{kind}-00001-of-*.safetensors"))
    return first[0] if first else None


class ReferenceModelError(CosyLiteError):
    """A reference-model set that does not exist or whose files are unusable; names the file and field."""


@dataclass
class ReferenceModels:
    """One set: ``weights[kind]`` the ``.safetensors`` files present, ``cards[kind]`` their cards,
    ``pipeline`` the set's inference settings and end-to-end metrics."""

    name: str
    folder: Path
    weights: dict[str, Path]
    cards: dict[str, dict[str, Any]]
    pipeline: dict[str, Any] = field(default_factory=dict)

    def path(self, kind: str) -> Path | None:
        """The weights file of ``kind`` (:data:`KINDS`), None if the set has none."""
        return self.weights.get(kind)

    @property
    def dataset(self) -> str:
        """The dataset the set was trained on (its cards' and pipeline's ``dataset``; else its name)."""
        for record in (self.pipeline, *self.cards.values()):
            if isinstance(record.get("dataset"), str):
                return record["dataset"]
        return self.name

    @property
    def pipeline_path(self) -> Path:
        return self.folder / PIPELINE_FILE

    @property
    def inference(self) -> dict[str, Any]:
        """How the set is meant to run: the ``inference`` of its ``pipeline.json``, the differences
        from the defaults of :class:`~cosy_lite.inference.settings.InferenceConfig` (which reads and
        checks them: :func:`~cosy_lite.inference.settings.inference_config`)."""
        return dict(self.pipeline.get("inference", {}))


def reference_names(root: Path | None = None) -> list[str]:
    """Names of the shipped sets (folders with at least one weights file)."""
    root = root or reference_root()
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and any(p.glob("*.safetensors")))


def _read_json(path: Path) -> dict[str, Any]:
    try:
        value = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ReferenceModelError(f"{path}: not readable JSON ({type(e).__name__}: {e})") from None
    if not isinstance(value, dict):
        raise ReferenceModelError(f"{path}: expected a JSON object, got {type(value).__name__}")
    return value


@functools.lru_cache(maxsize=None)
def _sha256(path: str, mtime_ns: int, size: int) -> str:
    """sha256 of a file; the cache key holds its mtime and size, so a changed file is hashed again."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def file_sha256(path: Path) -> str:
    """The sha256 (hex) of the file at ``path``, hashed once per process while it is unchanged."""
    st = path.stat()
    return _sha256(str(path.resolve()), st.st_mtime_ns, st.st_size)


def _files_of(folder: Path, kind: str) -> list[Path]:
    """The weights files of ``kind`` in ``folder``: ``KIND.safetensors`` and any ``KIND-*-of-*.safetensors``."""
    candidates = [folder / f"{kind}.safetensors", *folder.glob(f"{kind}-*-of-*.safetensors")]
    return sorted(p for p in candidates if p.is_file())


def checked_weights(card_path: Path, card: dict[str, Any], kind: str) -> list[Path]:
    """The weights files of the card ``card_path`` (its ``weights``), checked against the folder:
    the card's fields typed as :data:`CARD_FIELDS`; every file named there present, no other file of
    ``kind``, one file or all shards of one; sizes and sha256 as ``files`` gives them. Raises
    ReferenceModelError ``CARD: field 'F': ...`` naming the file."""
    from cosy_lite.weights.checkpoint import describe_value, shard_paths

    def fail(fld: str, problem: str) -> ReferenceModelError:
        return ReferenceModelError(f"{card_path}: field '{fld}': {problem}")

    for fld, (check, expected, required) in CARD_FIELDS.items():
        if fld not in card or card[fld] is None:
            if required:
                raise fail(fld, f"missing; expected {expected} (cards are written by scripts/publish_reference.py)")
        elif not check(card[fld]):
            raise fail(fld, f"expected {expected}, got {describe_value(card[fld])}")
    if card["kind"] != kind:
        raise fail("kind", f"{card['kind']!r} in the card of the {kind} network ({kind}.json)")
    folder, names = card_path.parent, card["weights"]
    if missing := [n for n in names if not (folder / n).is_file()]:
        raise fail("weights", f"names {missing[0]}, which is not in {folder}")
    if extra := [p.name for p in _files_of(folder, kind) if p.name not in names]:
        raise fail("weights", f"{extra[0]} is in {folder} but not in the card's list {names}: remove it, or "
                   "republish the network (scripts/publish_reference.py)")
    files = [folder / n for n in names]
    if shard_paths(files[0]) != files:
        raise fail("weights", f"{names} is not {kind}.safetensors, nor all shards {kind}-0000i-of-0000N.safetensors "
                   "in order")
    if unknown := sorted(set(card["files"]) - set(names)):
        raise fail("files", f"describes {unknown[0]}, which is not in the card's weights {names}")
    for path in files:
        entry, fld = card["files"].get(path.name), f"files[{path.name}]"
        if entry is None:
            raise fail(fld, f"missing: expected the size and sha256 of {path.name}")
        if (size := path.stat().st_size) != entry["bytes"]:
            raise fail(f"{fld}.bytes", f"{path} is {size} bytes, the card says {entry['bytes']} (a damaged or "
                       "replaced file)")
        if (digest := file_sha256(path)) != entry["sha256"]:
            raise fail(f"{fld}.sha256", f"{path} has sha256 {digest}, the card says {entry['sha256']} (a damaged or "
                       "replaced file)")
    total = sum(p.stat().st_size for p in files)
    if card.get("weights_bytes") is not None and card["weights_bytes"] != total:
        raise fail("weights_bytes", f"{card['weights_bytes']}, but the files {names} hold {total} bytes")
    return files


def reference_models(name: str, root: Path | None = None) -> ReferenceModels:
    """The set ``name``, each network's card checked against its files (:func:`checked_weights`).
    Raises ReferenceModelError listing the available names if there is none, and naming the file
    and the field for a set whose files do not agree with its cards."""
    root = root or reference_root()
    folder = root / name
    if not _NAME.match(name) or not folder.is_dir():
        raise ReferenceModelError(f"no reference models named {name!r} (available: {reference_names(root)})")
    pipeline = _read_json(folder / PIPELINE_FILE) if (folder / PIPELINE_FILE).is_file() else {}
    if not isinstance(pipeline.get("inference", {}), dict):
        raise ReferenceModelError(f"{folder / PIPELINE_FILE}: field 'inference': expected a JSON object of settings")
    cards, weights = {}, {}
    for kind in KINDS:
        card_path = folder / f"{kind}.json"
        if card_path.is_file():
            cards[kind] = _read_json(card_path)
            weights[kind] = checked_weights(card_path, cards[kind], kind)[0]
        elif files := _files_of(folder, kind):
            raise ReferenceModelError(f"{files[0]}: no card {card_path.name} beside it: every network of a set has "
                                      "one (written by scripts/publish_reference.py)")
    if not weights:
        raise ReferenceModelError(f"{folder}: no weights file ({', '.join(k + '.safetensors' for k in KINDS)})")
    return ReferenceModels(name, folder, weights, cards, pipeline)


def fill_networks(args: Any, ref: ReferenceModels, kinds: tuple[str, ...] = KINDS) -> None:
    """Set ``args.KIND`` (a command line's namespace) to the set's network of each of ``kinds``
    where the namespace has that attribute and it is None (a network given on the command line wins)."""
    for kind in kinds:
        if hasattr(args, kind) and getattr(args, kind) is None:
            setattr(args, kind, ref.path(kind))


def _same_weights(path: Path | None, ckpt: Any) -> bool:
    """Whether the weights file at ``path`` holds ``ckpt``'s step and tensors (as fp16)."""
    import torch

    from cosy_lite.weights.checkpoint import CheckpointError, load_weights

    if path is None:
        return False
    try:
        old = load_weights(path)
    except CheckpointError:
        return False
    half = {k: v.half().float() if v.is_floating_point() else v for k, v in ckpt.model.items()}
    return (old.step == ckpt.step and old.kind == ckpt.kind and old.model.keys() == half.keys()
            and all(torch.equal(old.model[k], half[k]) for k in half))


def card_files(files: list[Path]) -> dict[str, dict[str, Any]]:
    """The ``files`` field of a card: each weights file's name -> {"bytes": size, "sha256": hex digest}."""
    return {f.name: {"bytes": f.stat().st_size, "sha256": file_sha256(f)} for f in files}


def publish(checkpoint: str | Path, folder: str | Path, card: dict[str, Any]) -> tuple[list[Path], Path]:
    """Write the network of a training ``checkpoint`` into the set ``folder`` as fp16
    ``KIND.safetensors`` (sharded above :data:`MAX_FILE_BYTES`) and its card ``KIND.json``: ``card``
    (command, machine, metrics ...) plus what the checkpoint knows (kind, dataset, object ids, step,
    config, training seconds) and the files (``weights``; ``files``: size and sha256 of each).
    Returns (the weights files, the card)."""
    from cosy_lite.weights.checkpoint import load_checkpoint, save_weights, shard_paths

    ckpt = load_checkpoint(checkpoint)
    if ckpt.kind not in KINDS:
        raise ReferenceModelError(f"{checkpoint}: kind {ckpt.kind!r} is not one of {KINDS}")
    folder = Path(folder)
    old = weights_file(folder, ckpt.kind)
    unsharded_large = old is not None and old.name == f"{ckpt.kind}.safetensors" and old.stat().st_size > MAX_FILE_BYTES + 2**16
    # (a card update leaves the weights files as they are)
    if old is not None and _same_weights(old, ckpt) and not unsharded_large:
        files = shard_paths(old)
    else:
        stale = shard_paths(old) if old is not None else []
        files = save_weights(folder / f"{ckpt.kind}.safetensors", ckpt, max_shard_bytes=MAX_FILE_BYTES)
        for f in stale:
            if f not in files:
                f.unlink()
    known = {"kind": ckpt.kind, "dataset": ckpt.meta.get("dataset", ckpt.config.get("dataset")),
             "obj_ids": ckpt.meta.get("obj_ids") or ckpt.meta.get("label_map", {}).get("obj_ids"),
             "steps": ckpt.step, "training_seconds": round(float(ckpt.train_state.get("elapsed_s", 0.0)), 1),
             "weights": [f.name for f in files], "weights_bytes": sum(f.stat().st_size for f in files),
             "files": card_files(files), "weights_dtype": "float16", "config": ckpt.config}
    card_path = folder / f"{ckpt.kind}.json"
    card_path.write_text(json.dumps({**known, **card}, indent=1) + "\n")
    return files, card_path

"""Reference models: trained networks kept in the repository, one folder per dataset.

``models/NAME/`` of the repository (installed as the package data ``cosy_lite/reference/weights/NAME/``;
or ``$COSY_LITE_MODELS/NAME/``) holds, for the dataset
NAME (e.g. ``ycbvsynth``), each trained network as ``KIND.safetensors`` or, above
:data:`MAX_FILE_BYTES`, its shards ``KIND-0000i-of-0000N.safetensors`` (fp16 weights + the training
config and metadata as JSON, :func:`~cosy_lite.model_files.checkpoint.save_weights`: loading runs no
code) with its card ``KIND.json`` (dataset, object ids, exact training command, steps, crops seen,
wall time, machine, held-out metrics), and ``pipeline.json``: how the set is meant to run (start
poses, candidates, refiner iterations) and what the whole pipeline measured on the dataset's test split.

:func:`reference_models` finds a set by name (``Predictor.from_pretrained(NAME)``, ``infer.py
--pretrained NAME``); :func:`publish` writes one network of a set from a training run.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cosy_lite.errors import CosyLiteError

KINDS = ("detector", "coarse", "refiner")
PIPELINE_FILE = "pipeline.json"
# infer.py settings of a set when its pipeline.json does not say otherwise
DEFAULT_PIPELINE = {"start": "coarse", "n_candidates": 1, "n_refiner_iterations": 4}
_NAME = re.compile(r"^[A-Za-z0-9]+$")  # a BOP dataset name: no '_' or '-'


MAX_FILE_BYTES = 4 * 2**20  # larger weights are sharded: the repository keeps no file over 5 MB


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
        """The weights file of ``kind`` ("detector", "coarse", "refiner"), None if the set has none."""
        return self.weights.get(kind)

    def setting(self, key: str) -> Any:
        """An inference setting of :data:`DEFAULT_PIPELINE` as the set's ``pipeline.json`` gives it."""
        return self.pipeline.get("inference", {}).get(key, DEFAULT_PIPELINE[key])


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


def reference_models(name: str, root: Path | None = None) -> ReferenceModels:
    """The set ``name``. Raises ReferenceModelError listing the available names if there is none."""
    root = root or reference_root()
    folder = root / name
    if not _NAME.match(name) or not folder.is_dir():
        raise ReferenceModelError(f"no reference models named {name!r} (available: {reference_names(root)})")
    weights = {k: w for k in KINDS if (w := weights_file(folder, k)) is not None}
    if not weights:
        raise ReferenceModelError(f"{folder}: no weights file ({', '.join(k + '.safetensors' for k in KINDS)})")
    cards = {k: _read_json(folder / f"{k}.json") for k in weights if (folder / f"{k}.json").is_file()}
    pipeline = _read_json(folder / PIPELINE_FILE) if (folder / PIPELINE_FILE).is_file() else {}
    for key, value in pipeline.get("inference", {}).items():
        if key not in DEFAULT_PIPELINE or type(value) is not type(DEFAULT_PIPELINE[key]):
            raise ReferenceModelError(f"{folder / PIPELINE_FILE}: field 'inference.{key}' = {value!r} is not one of "
                                      f"{ {k: type(v).__name__ for k, v in DEFAULT_PIPELINE.items()} }")
    return ReferenceModels(name, folder, weights, cards, pipeline)


def fill_arguments(args: Any, use_networks: bool = True) -> None:
    """Complete a command line's namespace from its ``--pretrained NAME`` (``args.pretrained``): where
    the namespace has them and they are None, ``args.start`` / ``args.candidates`` (the set's
    settings, else the defaults of :data:`DEFAULT_PIPELINE`); then the set's networks where
    ``args.detector`` / ``.refiner`` are None, and ``.coarse`` when the poses start from it
    (``use_networks`` False: networks left as they are, for a backend that does not take them).
    Raises ReferenceModelError for an unknown name."""
    settings = {"start": DEFAULT_PIPELINE["start"], "candidates": DEFAULT_PIPELINE["n_candidates"]}
    ref = reference_models(args.pretrained) if getattr(args, "pretrained", None) is not None and use_networks else None
    if ref is not None:
        settings = {"start": ref.setting("start"), "candidates": ref.setting("n_candidates")}
        if getattr(args, "start", None) not in (None, settings["start"]):
            settings["candidates"] = 1  # the set's candidate count belongs to its own start
    for key, value in settings.items():
        if hasattr(args, key) and getattr(args, key) is None:
            setattr(args, key, value)
    if ref is not None:
        for kind in KINDS:  # the coarse network only where the poses start from it (export: all)
            if getattr(args, kind) is None and (kind != "coarse" or getattr(args, "start", "coarse") == "coarse"):
                setattr(args, kind, ref.path(kind))


def _same_weights(path: Path | None, ckpt: Any) -> bool:
    """Whether the weights file at ``path`` holds ``ckpt``'s step and tensors (as fp16)."""
    import torch

    from cosy_lite.model_files.checkpoint import CheckpointError, load_weights

    if path is None:
        return False
    try:
        old = load_weights(path)
    except CheckpointError:
        return False
    half = {k: v.half().float() if v.is_floating_point() else v for k, v in ckpt.model.items()}
    return (old.step == ckpt.step and old.kind == ckpt.kind and old.model.keys() == half.keys()
            and all(torch.equal(old.model[k], half[k]) for k in half))


def publish(checkpoint: str | Path, folder: str | Path, card: dict[str, Any]) -> tuple[list[Path], Path]:
    """Write the network of a training ``checkpoint`` into the set ``folder`` as fp16
    ``KIND.safetensors`` (sharded above :data:`MAX_FILE_BYTES`) and its card ``KIND.json``: ``card``
    (command, machine, metrics ...) plus what the checkpoint knows (kind, dataset, object ids, step,
    config, training seconds). Returns (the weights files, the card)."""
    from cosy_lite.model_files.checkpoint import load_checkpoint, save_weights, shard_paths

    ckpt = load_checkpoint(checkpoint)
    if ckpt.kind not in KINDS:
        raise ReferenceModelError(f"{checkpoint}: kind {ckpt.kind!r} is not one of {KINDS}")
    folder = Path(folder)
    old = weights_file(folder, ckpt.kind)
    unsharded_large = old is not None and old.name == f"{ckpt.kind}.safetensors" and old.stat().st_size > MAX_FILE_BYTES + 2**16
    if _same_weights(old, ckpt) and not unsharded_large:  # (a card update leaves the weights files as they are)
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
             "weights_dtype": "float16", "config": ckpt.config}
    card_path = folder / f"{ckpt.kind}.json"
    card_path.write_text(json.dumps({**known, **card}, indent=1) + "\n")
    return files, card_path

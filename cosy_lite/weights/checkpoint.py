"""Self-describing checkpoints: weights + full config + version + training state, written atomically.

One file per run folder (``checkpoint.pt``) is rewritten every ``checkpoint_every`` steps: the new
file is written next to it (``.checkpoint.pt.tmpPID``) and moved over it with :func:`os.replace`,
so a run killed at any moment (even ``kill -9``) leaves either the previous or the new checkpoint,
never a truncated one; :func:`remove_stale_temporaries` deletes what a killed write left behind.

Loading never runs code: files are read with ``torch.load(weights_only=True)`` (tensors and plain
data only), so a crafted file that would execute a payload when unpickled is refused with a
:class:`CheckpointError`. :func:`save_checkpoint` therefore stores plain data only (dicts, lists,
tuples, str, numbers, bools, None, tensors): dataclasses become dicts, paths strings.

Trained weights that leave a run to be handed on (the GPU run's results, reference models) are
``.safetensors`` files (:func:`save_weights`): the model's tensors (floating point ones in fp16 by
default) and, in safetensors' string metadata, the kind, step, full config and model metadata as
JSON, without the optimiser. Reading them parses tensors and JSON only; :func:`load_checkpoint` reads
them too (by their suffix), so every loader of checkpoints accepts them.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import torch

import cosy_lite
from cosy_lite.errors import CosyLiteError

CHECKPOINT_FORMAT = 1
REQUIRED_KEYS = ("format", "kind", "model", "config", "step")
WEIGHTS_FORMAT = "cosy_lite-weights-1"
WEIGHTS_SUFFIX = ".safetensors"
_WEIGHTS_FIELDS = ("format", "kind", "step", "config", "meta", "version")


TMP_INFIX = ".tmp"  # temporary file of a write in progress: .NAME.tmpPID
# Leaf types a weights-only torch.load reads back (besides containers).
PLAIN_LEAVES = (str, bytes, bool, int, float, complex, type(None), torch.Tensor, torch.Size, torch.dtype, torch.device)


class CheckpointError(CosyLiteError):
    """A checkpoint file (or the run folder's ``log.jsonl``) that cannot be used; the message names
    the file and what is wrong."""

    def __init__(self, path: str | Path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)


@dataclass
class Checkpoint:
    """Contents of a checkpoint file.

    kind: which model ("detector", "coarse", "refiner", ...); model: state_dict of the bare (not
    DDP-wrapped) module; config: the full training config as a plain dict; step: optimisation steps
    done; train_state: optimiser/scheduler/scaler states for resuming; meta: anything the model
    needs to be rebuilt and used (e.g. label map, object ids).
    """

    kind: str
    model: dict[str, torch.Tensor]
    config: dict[str, Any]
    step: int
    train_state: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    version: str = cosy_lite.__version__


def plain_data(obj: Any, where: str = "checkpoint") -> Any:
    """``obj`` as data a weights-only ``torch.load`` reads back: dataclasses -> dicts, paths ->
    str, numpy scalars -> Python numbers; containers rebuilt only where something changed (a
    state_dict keeps its type and metadata). TypeError naming the key for anything else."""
    if isinstance(obj, PLAIN_LEAVES):
        return obj
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return plain_data(dataclasses.asdict(obj), where)
    if isinstance(obj, PurePath):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, (str, int, float, bool, type(None))):
                raise TypeError(f"{where}: key {k!r} of type {type(k).__name__} cannot be stored (use str or int keys)")
            out[k] = plain_data(v, f"{where}.{k}")
        return obj if all(out[k] is obj[k] for k in obj) else out
    if isinstance(obj, (list, tuple, set)):
        items = [plain_data(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        if all(a is b for a, b in zip(items, obj)):
            return obj
        return items if isinstance(obj, list) else tuple(items) if isinstance(obj, tuple) else set(items)
    raise TypeError(f"{where}: a {type(obj).__module__}.{type(obj).__name__} cannot be stored in a weights-only "
                    "checkpoint (plain dicts, lists, str, numbers and tensors only)")


def temporary_path(path: str | Path) -> Path:
    """Where :func:`save_checkpoint` writes ``path`` before moving it into place (this process)."""
    path = Path(path)
    return path.with_name(f".{path.name}{TMP_INFIX}{os.getpid()}")


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Delete the temporary files of ``path`` left by killed writes (not this process's); return them."""
    path = Path(path)
    mine = temporary_path(path)
    stale = [p for p in path.parent.glob(f".{path.name}{TMP_INFIX}*") if p != mine and p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def save_checkpoint(path: str | Path, ckpt: Checkpoint) -> None:
    """Write ``ckpt`` to ``path`` atomically (temporary file in the same folder + fsync + rename).

    Everything is stored as plain data (:func:`plain_data`), so :func:`load_checkpoint` reads it
    weights-only; TypeError naming the key for a value that cannot be.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(path)
    payload = plain_data({
        "format": CHECKPOINT_FORMAT,
        "kind": ckpt.kind,
        "model": ckpt.model,
        "config": ckpt.config,
        "step": ckpt.step,
        "train_state": ckpt.train_state,
        "meta": ckpt.meta,
        "version": ckpt.version,
    })
    try:
        with open(tmp, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # only after a failed write (disk full, ...): replaced files are gone


def _refusal(e: Exception) -> str:
    """What a weights-only load refused, without torch's advice on how to load the file unsafely."""
    if found := re.search(r"GLOBAL ([\w.]+)", str(e)):
        return f"it asks for the Python object {found.group(1)}"
    found = re.search(r"WeightsUnpickler error:\s*([^.\n]+)", str(e))
    return found.group(1).strip() if found else " ".join(str(e).split())[:200]


def is_id_list(value: Any) -> bool:
    """Whether ``value`` is a non-empty list (or tuple) of positive integers: object ids."""
    return (isinstance(value, (list, tuple)) and len(value) > 0
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value))


def describe_value(value: Any) -> str:
    """``TYPE VALUE`` (shortened) for an "expected X, got ..." message."""
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) <= 60 else text[:57] + '...'}"


def _check_fields(path: Path, payload: dict[str, Any]) -> None:
    """CheckpointError naming the field when a field has the wrong type."""
    if not isinstance(payload["kind"], str):
        raise CheckpointError(path, f"field 'kind' must be a string, found {payload['kind']!r}")
    step = payload["step"]
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise CheckpointError(path, f"field 'step' must be a non-negative integer, found {step!r}")
    for name in ("model", "config", "train_state", "meta"):
        if not isinstance(payload.get(name, {}), dict):
            raise CheckpointError(path, f"field '{name}' must be a dict, found {type(payload[name]).__name__}")
    bad = [k for k, v in payload["model"].items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise CheckpointError(path, f"field 'model' must map parameter names to tensors; not so for {bad[:5]}")


def load_checkpoint(path: str | Path, kind: str | tuple[str, ...] | None = None) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint` (on CPU).

    Never runs code from the file (weights-only unpickling). Raises CheckpointError naming the file
    when it is missing, unreadable/truncated, holds Python objects beyond weights and plain data (a
    possible code payload: refused, nothing executed), lacks a field, has another format version,
    or holds another kind of model than ``kind``.
    """
    path = Path(path)
    ckpt = load_weights(path) if path.suffix == WEIGHTS_SUFFIX else _load_torch_checkpoint(path)
    kinds = (kind,) if isinstance(kind, str) else kind
    if kinds is not None and ckpt.kind not in kinds:
        raise CheckpointError(path, f"field 'kind' is {ckpt.kind!r}, expected one of {list(kinds)}")
    return ckpt


def _load_torch_checkpoint(path: Path) -> Checkpoint:
    if not path.is_file():
        raise CheckpointError(path, "checkpoint file not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        if "GLOBAL" not in str(e):  # garbage, not a request for Python objects
            raise CheckpointError(path, f"not a readable checkpoint ({_refusal(e)})") from None
        raise CheckpointError(path, "refused: the file holds Python objects, not only weights and plain data, and "
                                    f"loading it could run code ({_refusal(e)}); checkpoints are loaded weights-only "
                                    "(write them with cosy_lite's save_checkpoint)") from None
    except Exception as e:  # truncated zip, not a torch file, ...
        msg = " ".join(str(e).splitlines())
        raise CheckpointError(path, f"not a readable checkpoint ({type(e).__name__}: {msg})") from None
    if not isinstance(payload, dict):
        raise CheckpointError(path, f"expected a dict, found {type(payload).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in payload]
    if missing:
        raise CheckpointError(path, f"missing field(s) {missing}")
    if payload["format"] != CHECKPOINT_FORMAT:
        raise CheckpointError(path, f"field 'format' is {payload['format']}, this version reads {CHECKPOINT_FORMAT}")
    _check_fields(path, payload)
    return Checkpoint(
        kind=payload["kind"],
        model=payload["model"],
        config=payload["config"],
        step=payload["step"],
        train_state=payload.get("train_state", {}),
        meta=payload.get("meta", {}),
        version=payload.get("version", "?"),
    )


def _tuples_as_lists(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _tuples_as_lists(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_tuples_as_lists(v) for v in value]
    return value


def _plain_json(value: Any, path: Path, field: str) -> str:
    """JSON of ``value``; tuples become lists (configs read either), anything else must come back equal."""
    text = json.dumps(value, sort_keys=True)
    if json.loads(text) != _tuples_as_lists(value):  # e.g. a dict with int keys, a NaN, a tensor
        raise CheckpointError(path, f"field '{field}' does not survive JSON unchanged; expected plain JSON data")
    return text


_SHARD = re.compile(r"^(?P<stem>.+)-(?P<i>\d{5})-of-(?P<n>\d{5})\.safetensors$")


def shard_paths(path: str | Path) -> list[Path]:
    """The files of the weights ``path``: itself, or for a shard ``STEM-0000i-of-0000N.safetensors``
    all N shards (what :func:`save_weights` writes with ``max_shard_bytes``)."""
    path = Path(path)
    m = _SHARD.match(path.name)
    if m is None:
        return [path]
    n = int(m["n"])
    return [path.with_name(f"{m['stem']}-{i:05d}-of-{n:05d}.safetensors") for i in range(1, n + 1)]


def _shards(tensors: dict[str, torch.Tensor], max_bytes: int | None) -> list[dict[str, torch.Tensor]]:
    """``tensors`` split in order into groups of at most ``max_bytes`` (a larger tensor alone)."""
    groups: list[dict[str, torch.Tensor]] = [{}]
    size = 0
    for k, v in tensors.items():
        n = v.numel() * v.element_size()
        if max_bytes is not None and groups[-1] and size + n > max_bytes:
            groups.append({})
            size = 0
        groups[-1][k] = v
        size += n
    return groups


def save_weights(path: str | Path, ckpt: Checkpoint, dtype: torch.dtype = torch.float16,
                 max_shard_bytes: int | None = None) -> list[Path]:
    """Write ``ckpt``'s model (floating tensors as ``dtype``) + kind, step, config, meta (atomically),
    as ``path``, or with ``max_shard_bytes`` as shards ``STEM-00001-of-0000N.safetensors`` beside it
    when one file would be larger (each carries the metadata). Returns the files written."""
    from safetensors.torch import save_file

    path = Path(path)
    tensors = {k: (v.detach().to(dtype) if v.is_floating_point() else v.detach()).contiguous().cpu()
               for k, v in ckpt.model.items()}
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(path, f"tensors {bad[:5]} are not finite in {dtype} (overflow?); expected finite weights")
    meta = {"format": WEIGHTS_FORMAT, "kind": ckpt.kind, "step": str(int(ckpt.step)),
            "config": _plain_json(ckpt.config, path, "config"), "meta": _plain_json(ckpt.meta, path, "meta"),
            "version": cosy_lite.__version__}
    path.parent.mkdir(parents=True, exist_ok=True)
    groups = _shards(tensors, max_shard_bytes)
    n = len(groups)
    stem = path.name.removesuffix(WEIGHTS_SUFFIX)
    paths = [path] if n == 1 else [path.with_name(f"{stem}-{i:05d}-of-{n:05d}{WEIGHTS_SUFFIX}") for i in range(1, n + 1)]
    for group, out in zip(groups, paths):
        tmp = temporary_path(out)
        try:
            save_file(group, str(tmp), metadata=meta)
            tmp.replace(out)
        finally:
            tmp.unlink(missing_ok=True)
    return paths


def _read_weights_file(path: Path) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    from safetensors import SafetensorError, safe_open

    if not path.is_file():
        raise CheckpointError(path, "weights file not found")
    try:
        with safe_open(str(path), framework="pt") as f:
            return f.metadata() or {}, {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise CheckpointError(path, f"not a readable safetensors file ({type(e).__name__}: {str(e).splitlines()[0]})") from None


def load_weights(path: str | Path) -> Checkpoint:
    """The :class:`Checkpoint` of a weights file, or of all shards of a sharded one given any of them
    (float32 tensors; no training state). Raises :class:`CheckpointError` naming the file and field
    for anything unusable (a shard missing, shards of different networks)."""
    path = Path(path)
    header: dict[str, str] = {}
    tensors: dict[str, torch.Tensor] = {}
    for part in shard_paths(path):
        part_header, part_tensors = _read_weights_file(part)
        if header and any(part_header.get(k) != header.get(k) for k in ("kind", "step", "config", "meta")):
            raise CheckpointError(part, f"metadata differs from {path.name}'s: shards of another network")
        header = header or part_header
        tensors.update(part_tensors)
    missing = [k for k in _WEIGHTS_FIELDS if k not in header]
    if missing:
        raise CheckpointError(path, f"missing metadata field(s) {missing}: not a cosy_lite weights file")
    if header["format"] != WEIGHTS_FORMAT:
        raise CheckpointError(path, f"metadata field 'format' is {header['format']!r}, this version reads {WEIGHTS_FORMAT!r}")
    values = {}
    for key in ("step", "config", "meta"):
        try:
            values[key] = json.loads(header[key])
        except json.JSONDecodeError:
            raise CheckpointError(path, f"metadata field '{key}' is not JSON") from None
    if not isinstance(values["step"], int) or values["step"] < 0:
        raise CheckpointError(path, f"metadata field 'step' is {header['step']!r}; expected an integer >= 0")
    for key in ("config", "meta"):
        if not isinstance(values[key], dict):
            raise CheckpointError(path, f"metadata field '{key}' is not a JSON object")
    model = {k: v.float() if v.is_floating_point() else v for k, v in tensors.items()}
    return Checkpoint(kind=header["kind"], model=model, config=values["config"], step=values["step"],
                      meta=values["meta"], version=header["version"])

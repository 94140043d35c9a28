"""``train.py --init WEIGHTS``: start a training run from published weights (fine-tuning).

The weights file (a reference set's ``KIND.safetensors``, any shard of a sharded one, or a run's
``checkpoint.pt``) must hold the same kind of network with exactly the parameters the run builds; only
the weights are taken (the optimiser and the step start afresh). The one exception: parameters of a
module the network adds to what the file holds (``model.new_modules``, e.g. a flow refiner's depth
head) start at their initial values and are named in the record. What initialised the run is
recorded in every checkpoint's ``meta["init"]`` and from there in a published card, so a network
trained over several working periods says where each part came from.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from cosy_lite.weights.checkpoint import CheckpointError, load_checkpoint


def load_initial_weights(model: torch.nn.Module, path: str | Path, kind: str,
                         net: dict[str, Any] | None = None) -> dict[str, Any]:
    """Copy the ``kind`` network of ``path`` into ``model``; returns the record kept in the run's meta:
    ``{"path", "kind", "step", "items_seen"}`` (``items_seen``: the crops/images that trained the
    file's network, :func:`items_seen`; the file's own ``init`` record is kept under ``"init"``).

    Raises CheckpointError naming the file when it is another kind of network or its tensors do not
    fit ``model`` (missing, unexpected or differently shaped parameters); ``net`` (the run's ``net.*``
    settings) lets that error name the settings in which the file's network differs."""
    path = Path(path)
    ckpt = load_checkpoint(path, kind=kind)
    own = model.state_dict()
    fresh = sorted(k for k in set(own) - set(ckpt.model) if k.split(".")[0] in new_modules(model))
    missing = sorted(set(own) - set(ckpt.model) - set(fresh))
    unexpected = sorted(set(ckpt.model) - set(own))
    shapes = sorted(k for k in set(own) & set(ckpt.model) if tuple(own[k].shape) != tuple(ckpt.model[k].shape))
    if missing or unexpected or shapes:
        parts = [f"{name} {keys[:3]}" for name, keys in (("missing", missing), ("unexpected", unexpected),
                                                          ("differently shaped", shapes)) if keys]
        raise CheckpointError(path, "field 'model' does not fit the network this run builds ("
                              + "; ".join(parts) + "); expected weights of the same architecture ("
                              + _differing_settings(ckpt.meta.get("net"), net) + ")")
    model.load_state_dict({k: v.to(own[k].dtype) for k, v in ckpt.model.items()}, strict=not fresh)
    record: dict[str, Any] = {"path": str(path), "kind": ckpt.kind, "step": int(ckpt.step),
                              "items_seen": items_seen(path, ckpt.meta)}
    if fresh:
        record["new_modules"] = sorted({k.split(".")[0] for k in fresh})
    if "init" in ckpt.meta:
        record["init"] = ckpt.meta["init"]
    return record


def _differing_settings(theirs: Any, ours: dict[str, Any] | None) -> str:
    """The ``net.*`` settings in which the file's network (its meta) differs from the run's, as
    ``net.KEY=FILE'S (this run: RUN'S)``; "net.* settings" when either side is unknown or none differs."""
    if not isinstance(theirs, dict) or not ours:
        return "net.* settings"
    keys = sorted(k for k in set(theirs) & set(ours) if theirs[k] != ours[k])
    if not keys:
        return "net.* settings"
    return "the file's " + ", ".join(f"net.{k}={theirs[k]!r} (this run: {ours[k]!r})" for k in keys)


def new_modules(model: torch.nn.Module) -> tuple[str, ...]:
    """Top-level modules of ``model`` that weights of an earlier network may lack (its ``new_modules``)."""
    inner = getattr(model, "module", model)  # DDP
    return tuple(getattr(inner, "new_modules", ()))


CARD_COUNTS = ("crops_seen", "images_seen")  # what a reference card calls the items behind its network


def items_seen(path: Path, meta: dict[str, Any]) -> int | None:
    """Training items (crops or images) behind the network of ``path``: ``meta["items_seen"]`` (written
    by the training loop), else the count on the reference card ``KIND.json`` beside the file; None
    when neither says."""
    count = meta.get("items_seen")
    if isinstance(count, int) and not isinstance(count, bool):
        return count
    card = path.with_name(f"{meta.get('model') or path.stem.split('-')[0]}.json")
    try:
        values = json.loads(card.read_text())
    except (OSError, ValueError):
        return None
    counts = [values.get(k) for k in CARD_COUNTS] if isinstance(values, dict) else []
    return next((c for c in counts if isinstance(c, int) and not isinstance(c, bool)), None)

"""Write a training run's network into the shipped reference models (fp16 safetensors + JSON card).

    python scripts/publish_reference.py --checkpoint runs/ref/detector/checkpoint.pt --name ycbvsynth \\
        --world-size 2 --command "OMP_NUM_THREADS=1 torchrun ... train.py ..." [--metrics X.json ...]

The card gets what the checkpoint knows (kind, dataset, object ids, steps, config, training seconds)
plus the command, the machine, the items seen (the checkpoint's count, including those of the weights it
was initialised from with --init; else steps x batch x processes), the --init record and any metric JSON files
given (merged under "metrics"). Folder: ``--out``, default ``models/NAME/`` of this
checkout (shipped in the package as data; ``$COSY_LITE_MODELS/NAME/`` when that is set), see
cosy_lite.weights.reference_models.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# the checkout's reference-model folder (not an installed copy's): published sets are committed here
REFERENCE_DIR = REPO / "models"


def default_folder(name: str) -> Path:
    """Where the set ``name`` is written: ``$COSY_LITE_MODELS/NAME``, else this checkout's :data:`REFERENCE_DIR`."""
    env = os.environ.get("COSY_LITE_MODELS")
    return (Path(env) if env else REFERENCE_DIR) / name


def main(argv: list[str] | None = None) -> int:
    from cosy_lite.weights.checkpoint import load_checkpoint
    from cosy_lite.weights.reference_models import publish

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--name", required=True, help="the set (dataset name), e.g. ycbvsynth")
    ap.add_argument("--command", required=True, help="the exact training command(s) that made the checkpoint")
    ap.add_argument("--out", type=Path, default=None, metavar="DIR",
                    help="the set's folder (default: $COSY_LITE_MODELS/NAME, else models/NAME)")
    ap.add_argument("--world-size", type=int, default=1, help="training processes (DDP)")
    ap.add_argument("--machine", default=f"{platform.machine()} CPU, {platform.node() or 'unknown'}; no GPU")
    ap.add_argument("--note", default="", help="anything else a user should know")
    ap.add_argument("--metrics", type=Path, nargs="*", default=[], metavar="JSON",
                    help="held-out metric files: each merged under metrics.<file stem>")
    args = ap.parse_args(argv)
    ckpt = load_checkpoint(args.checkpoint)
    batch = int(ckpt.config.get("loop", {}).get("batch_size", 0))
    unit = "images" if ckpt.kind == "detector" else "crops"
    card = {"training_command": args.command, "machine": args.machine, "processes": args.world_size,
            f"{unit}_seen": ckpt.meta.get("items_seen", ckpt.step * batch * args.world_size),
            "published": date.today().isoformat(), "init": ckpt.meta.get("init"),
            "source_checkpoint": str(args.checkpoint), "note": args.note,
            "metrics": {p.stem: json.loads(p.read_text()) for p in args.metrics}}
    weights, card_path = publish(args.checkpoint, args.out or default_folder(args.name), card)
    print(", ".join(f"{w} ({w.stat().st_size / 2**20:.2f} MiB)" for w in weights) + f"; {card_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

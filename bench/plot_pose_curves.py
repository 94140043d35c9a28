"""Learning curves of pose-network runs: held-out errors against training crops seen.

    python bench/plot_pose_curves.py OUT.png RUN_DIR [RUN_DIR ...] [--title TEXT]

A run folder holds ``log.jsonl`` with ``{"type": "val", "crops": N, "itN/rot_err_deg_median": ...,
"itN/trans_err_cm_median": ..., "itN/mssd_recall_0.1d": ...}`` records (the experiment harness in
``bench/curves/*/train_exp.py``) or the training loop's records (``"step"`` and ``"val/iterK/..."``
keys; crops = step x batch size from the run's ``config.yaml``). Panels: median rotation error,
median translation error, MSSD recall at 0.1 d (after the validation iterations) and the training loss.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def _series(run: Path) -> tuple[list[dict], list[dict]]:
    recs = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    val = [r for r in recs if r["type"] == "val"]
    train = [r for r in recs if r["type"] == "train"]
    if val and "crops" not in val[0]:  # the training loop's log
        import yaml

        cfg = yaml.safe_load((run / "config.yaml").read_text())
        batch = int(cfg["loop"]["batch_size"])
        it = f"iter{cfg.get('val_iterations', 4)}"
        val = [{"crops": r["step"] * batch, **{k.replace("val/", "").replace(it, "itN"): v for k, v in r.items()}} for r in val]
        train = [{"crops": r["step"] * batch, "total": r["loss/total"]} for r in train]
    return val, train


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--title", default="")
    args = ap.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(20, 4.6))
    keys = [("itN/rot_err_deg_median", "held-out median rotation error (deg)"),
            ("itN/trans_err_cm_median", "held-out median translation error (cm)"),
            ("itN/mssd_recall_0.1d", "held-out MSSD recall at 0.1 d")]
    for run in args.runs:
        val, train = _series(run)
        for ax, (k, _) in zip(axes, keys):
            ax.plot([r["crops"] for r in val], [r[k] for r in val], marker=".", label=run.name)
        if train:
            loss = [r.get("total", r.get("ce")) for r in train]  # flow-refiner harness logs: cross-entropy
            axes[3].plot([r["crops"] for r in train], loss, alpha=0.7, label=run.name)
    for ax, (_, title) in zip(axes, keys + [(None, "training loss (m; flow runs: cross-entropy)")]):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("training crops seen")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    if args.title:
        fig.suptitle(args.title)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

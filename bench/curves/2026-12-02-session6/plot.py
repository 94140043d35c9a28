"""Scratch: session 6's refiner curves on the 256 held-out instances (heldout_*.json of
heldout_refiner.py) beside session 3's E1 (192x256, from bench/RESULTS.md), with log-linear fits
of translation and rotation against crops seen and the halving targets. Usage: plot.py OUT.png"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).parent
INIT = (22.726, 4.087)  # the 256 instances before refinement (rot deg, trans cm)
TARGET = (INIT[0] / 2, INIT[1] / 2)
# session 3, run E1 (train.py, 192x256, batch 4 x 2 processes, augmentation off, constant lr), 256 held-out
E1 = {"crops": [9608, 20800, 24800, 28000, 31600, 37600], "rot": [14.4, 10.0, 11.7, 11.8, 13.0, 11.2],
      "trans": [4.38, 4.43, 3.55, 3.77, 4.27, 3.23]}
BATCH = 16  # crops per step in session 6's runs (8 per process x 2 DDP processes)


def series(prefix: str) -> dict[str, list[float]]:
    rows = []
    for f in sorted(HERE.glob(f"{prefix}*.json")):
        r = json.loads(f.read_text())
        rows.append((r["step"] * BATCH, r["it4"]["rot_err_deg_median"], r["it4"]["trans_err_cm_median"]))
    rows.sort()
    return {"crops": [a for a, _, _ in rows], "rot": [b for _, b, _ in rows], "trans": [c for _, _, c in rows]}


def fromgt() -> dict[str, list[float]]:
    rows = []
    for f in sorted(HERE.glob("fromgt_R0_*.json")):
        r = json.loads(f.read_text())
        rows.append((r["step"] * BATCH, r["it1"]["trans_err_cm_median"], r["it4"]["trans_err_cm_median"],
                     r["it4"]["rot_err_deg_median"]))
    rows.sort()
    return {"crops": [a[0] for a in rows], "t1": [a[1] for a in rows], "t4": [a[2] for a in rows], "r4": [a[3] for a in rows]}


def pipeline() -> dict[str, list[float]]:
    rows = []
    for f in sorted(HERE.glob("pipeline_r0s*.json")):
        step = int(f.stem.removeprefix("pipeline_r0s"))
        r = json.loads(f.read_text())
        rows.append((step * BATCH, r["mssd_recall_0.1d"], r["ar"]))
    rows.sort()
    return {"crops": [a[0] for a in rows], "recall": [a[1] for a in rows], "ar": [a[2] for a in rows]}


def loglin(ax, x, y, target, label, unit):
    if len(x) < 3:
        return
    fit = np.polyfit(np.log2(x), y, 1)
    xs = np.geomspace(min(x), 1e7, 60)
    ax.plot(xs, np.polyval(fit, np.log2(xs)), ":", color=ax.lines[-1].get_color(), alpha=0.7)
    better_down = target < y[0]
    ok = (fit[0] < 0) if better_down else (fit[0] > 0)
    reach = 2 ** ((target - fit[1]) / fit[0]) if ok else float("inf")
    print(f"{label}: {fit[0]:+.3f} {unit} per doubling of the crops; target {target:g} at ~{reach:,.0f} crops")


def main(out: str) -> None:
    runs = {"E1 192x256 (session 3)": E1}
    for prefix, label in (("heldout_R0", "R0: demo profile, augmentation off (long run)"),
                          ("heldout_R1", "R1 = R0 + cosine lr over 20 min")):
        s = series(prefix)
        if s["crops"]:
            runs[label] = s
    fig, axes = plt.subplots(1, 4, figsize=(22, 4.8))
    for ax, key, unit, target, init in ((axes[0], "rot", "deg", TARGET[0], INIT[0]), (axes[1], "trans", "cm", TARGET[1], INIT[1])):
        for label, s in runs.items():
            ax.plot(s["crops"], s[key], "o-", label=label)
            loglin(ax, s["crops"], s[key], target, f"{label} {key}", unit)
        ax.axhline(init, color="grey", lw=0.8, ls="--", label="before refinement")
        ax.axhline(target, color="red", lw=1, label="target (halved)")
        ax.axvline(11776, color="k", lw=0.6, ls="-.", label="20 min of R0 (2 processes, 144x192)")
        ax.set_xscale("log")
        ax.set_xlabel("training crops seen")
        ax.set_ylabel(f"median {key} error after 4 iterations ({unit})")
        ax.set_title(f"refiner from GT + noise, 256 held-out: {key}")
    axes[1].legend(fontsize=7)
    g = fromgt()
    ax = axes[2]
    if g["crops"]:
        ax.plot(g["crops"], g["t1"], "o-", label="translation after 1 iteration (cm)")
        ax.plot(g["crops"], g["t4"], "o-", label="translation after 4 iterations (cm)")
        loglin(ax, g["crops"], g["t4"], TARGET[1], "drift from GT, 4 iterations, trans", "cm")
        ax.plot(g["crops"], [r / 5 for r in g["r4"]], "s--", label="rotation after 4 iterations (deg / 5)")
    ax.axhline(TARGET[1], color="red", lw=1, label="translation target from noise (2.04 cm)")
    ax.set_xscale("log")
    ax.set_xlabel("training crops seen")
    ax.set_title("R0 started AT the GT pose: drift (256 held-out)")
    ax.legend(fontsize=7)
    pl = pipeline()
    ax = axes[3]
    ax.plot(pl["crops"], pl["recall"], "o-", label="MSSD recall at 0.1 d")
    loglin(ax, pl["crops"], pl["recall"], 0.5, "pipeline MSSD recall 0.1 d", "")
    ax.plot(pl["crops"], pl["ar"], "s-", label="AR")
    ax.plot([411 * BATCH], [0.048], "x", color="C0", ms=9, label="session 5's demo refiner (augmentation on): recall")
    ax.plot([411 * BATCH], [0.196], "x", color="C1", ms=9, label="... and AR")
    ax.axhline(0.5, color="red", lw=1, label="target recall 0.5")
    ax.set_xscale("log")
    ax.set_xlabel("refiner training crops seen")
    ax.set_title("GT masks + templates (top 5) + refiner, RGB, test split")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=100)


if __name__ == "__main__":
    main(sys.argv[1])

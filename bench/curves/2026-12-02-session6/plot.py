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


def main(out: str) -> None:
    runs = {"E1 192x256 (session 3)": E1}
    for prefix, label in (("heldout_R0", "R0 demo profile, augmentation off, constant lr"),
                          ("heldout_R1", "R1 = R0 + cosine lr over 20 min"),
                          ("heldout_R2", "R2 = demo profile as is (augmentation on)")):
        s = series(prefix)
        if s["crops"]:
            runs[label] = s
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, key, unit, target, init in ((axes[0], "rot", "deg", TARGET[0], INIT[0]), (axes[1], "trans", "cm", TARGET[1], INIT[1])):
        for label, s in runs.items():
            ax.plot(s["crops"], s[key], "o-", label=label)
            if len(s["crops"]) >= 3:
                c = np.array(s["crops"], float)
                fit = np.polyfit(np.log2(c), s[key], 1)
                xs = np.geomspace(c.min(), 1e6, 50)
                ax.plot(xs, np.polyval(fit, np.log2(xs)), ":", color=ax.lines[-1].get_color(), alpha=0.7)
                reach = 2 ** ((target - fit[1]) / fit[0]) if fit[0] < 0 else float("inf")
                print(f"{label} {key}: {fit[0]:+.2f} {unit} per doubling; target {target:.2f} at ~{reach:,.0f} crops")
        ax.axhline(init, color="grey", lw=0.8, ls="--", label="before refinement")
        ax.axhline(target, color="red", lw=1, label="target (halved)")
        ax.axvline(16 * 600, color="k", lw=0.6, ls="-.", label="~20 min, 2 processes, 144x192")
        ax.set_xscale("log")
        ax.set_xlabel("training crops seen")
        ax.set_ylabel(f"median {key} error after 4 iterations ({unit})")
        ax.set_title(f"refiner, 256 held-out instances: {key}")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    main(sys.argv[1])

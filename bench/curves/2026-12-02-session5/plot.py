"""Session 5 plot: AR of the ICP variants on the same demo models (scores/*.json) -> icp_variants_ar.png"""
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

here = Path(__file__).parent
rows = [  # (label, GT-masks file, detector file)
    ("A: before (15 deg / 5 cm limits,\nRGB choice only)", "A_cosyliteoracleicp", "A_cosyliteicp"),
    ("B: every candidate ICP'd,\nkept by depth agreement", "B_Boracleicp", "B_Bdeticp"),
    ("C: B + limits 180 deg / 15 cm", "C_Coracleicp", "C_Cdeticp"),
    ("D: B, no limits\n(agreement check decides)", "D_Doracleicp", None),
    ("E: D + 4 cm first stage\n(the new default)", "E_Eoracleicp", "E_Edeticp"),
]
fig, ax = plt.subplots(figsize=(9, 4))
x = np.arange(len(rows))
for k, (col, name) in enumerate(((1, "GT masks + ICP"), (2, "detector + ICP"))):
    vals = [json.loads((here / "scores" / f"{r[col]}.json").read_text())["ar"] if r[col] else np.nan for r in rows]
    bars = ax.bar(x + (k - 0.5) * 0.38, vals, 0.38, label=name)
    for b, v in zip(bars, vals):
        if np.isfinite(v):
            ax.text(b.get_x() + b.get_width() / 2, v + 0.01, f"{v:.3f}", ha="center", fontsize=8)
ax.axhline(0.3, color="grey", ls="--", lw=1)
ax.text(2.6, 0.31, "issue 13 target, GT + ICP", fontsize=7, ha="center", color="grey")
ax.set_xticks(x, [r[0] for r in rows], fontsize=7)
ax.set_ylabel("BOP19 AR (test split, 100 images)")
ax.set_ylim(0, 0.65)
ax.legend(fontsize=8, loc="upper left")
ax.set_title("Depth ICP variants, same demo models (detector 18 min, refiner 11 min), templates top 5")
fig.tight_layout()
fig.savefig(here / "icp_variants_ar.png", dpi=110)

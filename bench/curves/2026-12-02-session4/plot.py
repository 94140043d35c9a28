"""AR on the ycbv-synth test split by start pose (bench/RESULTS.md, "Silhouette-template start poses")."""
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).parent
RUNS = [  # label, scores file
    ("GT boxes + coarse net (baseline)", "scores_baseline_cosyliteoracle.json"),
    ("GT masks + templates, top 1", "scores_oracleK1.json"),
    ("GT masks + templates, top 3", "scores_oracleK3.json"),
    ("GT masks + templates, top 5", "scores_oracleK5.json"),
    ("GT boxes + coarse net + ICP (baseline)", "scores_baseline_cosyliteoracleicp.json"),
    ("GT masks + templates top 5 + ICP", "scores_oracleicpK5.json"),
    ("detector + coarse net (baseline)", "scores_baseline_cosylite.json"),
    ("detector + templates, top 5", "scores_detK5.json"),
]
keys = ["ar", "ar_vsd", "ar_mssd", "ar_mspd"]
fig, ax = plt.subplots(figsize=(9, 4))
w = 0.8 / len(RUNS)
for i, (label, f) in enumerate(RUNS):
    s = json.loads((HERE / f).read_text())
    ax.bar([k + i * w - 0.4 + w / 2 for k in range(len(keys))], [s[k] for k in keys], w, label=label)
ax.set_xticks(range(len(keys)), ["AR", "AR_VSD", "AR_MSSD", "AR_MSPD"])
ax.set_ylabel("recall")
ax.set_ylim(0, 0.36)
ax.set_title("ycbv-synth test (100 images, 812 targets); the same 11-min refiner and detector (demo of 5c0d441)")
ax.legend(fontsize=7, ncol=2)
fig.tight_layout()
fig.savefig(HERE / "template_start_ar.png", dpi=110)

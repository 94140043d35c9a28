"""Plot of this session's refiner curve (train.py, 64 vs 256 held-out instances) and coarse candidates.

Usage: python bench/curves/2026-12-02-session3/plot.py  (reads the logs next to it, writes session3_curves.png)
"""
from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).parent
CROPS_PER_STEP = 8  # 2 DDP processes x batch 4


def main() -> None:
    vals = [json.loads(line) for line in (HERE / "E1_train_py_refiner_ddp_b4_noaug" / "log.jsonl").open()]
    vals = [v for v in vals if v.get("type") == "val"]
    big = json.loads((HERE / "E1_train_py_refiner_ddp_b4_noaug" / "heldout256_by_step.json").read_text())
    fig, ax = plt.subplots(1, 3, figsize=(16, 4.5))
    for k, (key, big_key, name, target) in enumerate([
        ("val/iter4/rot_err_deg_median", "rot_err_deg_median", "rotation error (deg), median", 22.5 / 2),
        ("val/iter4/trans_err_cm_median", "trans_err_cm_median", "translation error (cm), median", 4.22 / 2),
        ("val/iter4/mssd_recall_0.1d", "mssd_recall_0.1d", "MSSD recall at 0.1 d", None),
    ]):
        a = ax[k]
        a.plot([v["step"] * CROPS_PER_STEP for v in vals], [v[key] for v in vals], "o-",
               label="64 held-out (train.py validation)")
        steps = sorted(int(s) for s in big)
        a.plot([s * CROPS_PER_STEP for s in steps], [big[str(s)]["it4"][big_key] for s in steps], "s-",
               label="256 held-out (diag_refiner.py)")
        a.axhline(big[str(steps[0])]["init"][big_key], color="gray", ls=":", label="before (256)")
        if target is not None:
            a.axhline(target, color="red", ls="--", label="target: halved")
        a.set_xlabel("training crops")
        a.set_title(name + ", 4 iterations")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle("Flow refiner, python train.py (2 DDP processes x batch 4, 192x256, augmentation off), "
                 "GT + 15 deg / (1, 1, 5) cm")
    fig.tight_layout()
    fig.savefig(HERE / "session3_curves.png", dpi=110)
    print(HERE / "session3_curves.png")


if __name__ == "__main__":
    main()

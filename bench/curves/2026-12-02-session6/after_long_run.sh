#!/usr/bin/env bash
# Scratch: after the long run R0 (runs/s6/R0_noaug) stops: the final checkpoint on the 256 held-out
# instances (from noise and from GT), the snapshots from GT, and the RGB pipeline for two of them,
# two processes at a time.
set -uo pipefail
here=bench/curves/2026-12-02-session6
run=runs/s6/R0_noaug
step=$(printf %05d "$(python3 -c "import json; print([json.loads(l) for l in open('$run/log.jsonl')][-1]['step'])")")
cp $run/checkpoint.pt $run/snap_$step.pt
h() { OMP_NUM_THREADS=1 .venv/bin/python $here/heldout_refiner.py "$@" 2>&1 | grep -v Warn; }
h $run/snap_$step.pt --out $here/heldout_R0_$step.json > $here/heldout_R0_$step.log &
h $run/snap_$step.pt --from-gt --out $here/fromgt_R0_$step.json > $here/fromgt_R0_$step.log
wait
for s in $run/snap_*.pt; do
  n=$(basename $s .pt | sed 's/snap_//')
  [[ -f $here/fromgt_R0_$n.json || $n == "$step" ]] || h $s --from-gt --out $here/fromgt_R0_$n.json > $here/fromgt_R0_$n.log
done
bash $here/pipeline_rgb.sh $run/snap_01590.pt r0s01590 &
bash $here/pipeline_rgb.sh $run/snap_$step.pt r0s$step
wait

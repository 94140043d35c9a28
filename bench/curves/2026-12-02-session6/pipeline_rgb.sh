#!/usr/bin/env bash
# Scratch: GT masks (oracle) + silhouette templates (top 5) + a refiner checkpoint, RGB only, on the
# ycbv-synth test split (100 images), then the BOP19 evaluation: MSSD recall at 0.1 d from GT boxes/masks
# against the refiner's training crops. Usage: pipeline_rgb.sh CKPT METHOD (one thread, niced)
set -euo pipefail
ckpt=$1; method=$2
here=$(dirname "$0")
OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python infer.py --dataset data/ycbvsynth --start templates --candidates 5 \
  --templates-cache runs/demo/templates --refiner "$ckpt" --detections oracle --method "$method" \
  --out runs/s6/results --threads 1 --no-progress > "$here/pipeline_$method.log" 2>&1
OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m cosy_lite.cli eval --dataset data/ycbvsynth \
  --results "runs/s6/results/${method}_ycbvsynth-test.csv" --out "runs/s6/results/${method}_eval" --workers 1 --no-progress >> "$here/pipeline_$method.log" 2>&1
python3 -c "
import json; d = json.load(open('runs/s6/results/${method}_eval/scores.json'))
out = {k: d[k] for k in ('ar', 'ar_vsd', 'ar_mssd', 'ar_mspd', 'recall_mssd', 'thresholds')}
out['mssd_recall_0.1d'] = d['recall_mssd'][1]
json.dump(out, open('$here/pipeline_$method.json', 'w'), indent=1); print('$method', out['ar'], out['mssd_recall_0.1d'])"

#!/usr/bin/env bash
# Session 5 A/B of the ICP stage on the demo's trained models (runs of /work/main's cosy-lite demo).
# usage: measure.sh NAME DETECTIONS(oracle|detector) [infer.py args...]   -> $OUT/NAME_ycbvsynth-test.csv + _eval
set -euo pipefail
name=$1; src=$2; shift 2
MAIN=/work/main; OUT=${OUT:-/work/meas}
export PYOPENGL_PLATFORM=egl OMP_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE PYTHONPATH=/work/wt
det=(--detections oracle)
[ "$src" = detector ] && det=(--detector $MAIN/runs/demo/detector/checkpoint.pt)
cd /work/wt
$MAIN/.venv/bin/python infer.py --dataset $MAIN/data/ycbvsynth --start templates --candidates 5 \
  --templates-cache $MAIN/runs/demo/templates --refiner $MAIN/runs/demo/refiner/checkpoint.pt --n-refiner-iters 4 \
  --threads 1 --method "$name" --out $OUT --no-progress "${det[@]}" "$@" 2>&1 | grep -v Warning
for csv in $OUT/${name}_ycbvsynth-test.csv $OUT/${name}rgb_ycbvsynth-test.csv; do
  [ -f "$csv" ] && [ ! -f "${csv%.csv}_eval/scores.json" ] && \
    $MAIN/.venv/bin/python -m cosy_lite.cli eval --dataset $MAIN/data/ycbvsynth --results "$csv" --no-progress --workers 1 \
      | grep -E "^\| (AR|all)|AR " | head -3
done
true

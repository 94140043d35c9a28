#!/bin/bash
# infer.py (this checkout's code) with the baseline demo's checkpoints: templates, K candidates
set -e
cd /work/main
export PYOPENGL_PLATFORM=egl OMP_WAIT_POLICY=PASSIVE
R=/work/democlone/runs/demo
OUT=/work/meas
mkdir -p $OUT
for spec in "$@"; do
  IFS=: read name k extra <<< "$spec"
  csv=$OUT/${name}_ycbvsynth-test.csv
  if [ ! -f $csv ]; then
    /usr/bin/time -f "%e s wall" .venv/bin/python infer.py --dataset data/ycbvsynth --start templates --candidates $k \
      --templates-cache $OUT/templates --refiner $R/refiner/checkpoint.pt --threads 2 --method $name --out $OUT $extra --no-progress
  fi
  .venv/bin/python -m cosy_lite.cli eval --dataset data/ycbvsynth --results $csv --out $OUT/${name}_eval | tail -n 12
done

#!/usr/bin/env bash
# Usage: ab_time.sh SRC_TREE OUT (SRC_TREE: a checkout, imported through PYTHONPATH)
# A/B: per-image time of the reference pipeline (detector + templates top 5 + refiner x4 + ICP), 10 images
SRC=$1; OUT=$2
export PYTHONPATH=$SRC PYOPENGL_PLATFORM=egl OMP_WAIT_POLICY=PASSIVE
cd $SRC && /work/main/.venv/bin/python infer.py --dataset /work/data/ycbvsynth --pretrained ycbvsynth --icp --limit-images 10 --threads 1 --no-progress --out $OUT --templates-cache /work/data/tcache 2>&1 | grep "time per image"

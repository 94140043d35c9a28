#!/usr/bin/env bash
# Usage: poses_before_after.sh SRC_TREE OUT  (N=30 images; SRC_TREE: a checkout, used through PYTHONPATH;
# before = a worktree of 131fa9d, after = c993d91..2672f67). Writes torch (detector, +ICP and before it) and
# onnx (templates, 5 candidates) CSVs of the reference models on the first N test images.
# poses before/after the #17 refactor: $1 = source tree, $2 = out folder
set -euo pipefail
SRC=$1; OUT=$2; mkdir -p $OUT
export PYTHONPATH=$SRC PYOPENGL_PLATFORM=egl OMP_WAIT_POLICY=PASSIVE
PY=/work/main/.venv/bin/python
DATA=/work/data/ycbvsynth
cd $OUT
[ -f $DATA/test_targets_bop19.json ] || $PY -m cosy_lite.cli generate --out $DATA --workers 2 --splits test > gen.log 2>&1
$PY -c "import cosy_lite; print(cosy_lite.__file__)" > which.txt
$PY -m cosy_lite.cli export --pretrained ycbvsynth --out $OUT/onnx > export.log 2>&1
N=${N:-30}
( cd $SRC && $PY infer.py --dataset $DATA --pretrained ycbvsynth --icp --also-before-icp rgb --method icp --limit-images $N --threads 1 --templates-cache /work/data/tcache --no-progress --out $OUT/torch ) > torch.log 2>&1 &
( cd $SRC && $PY infer.py --dataset $DATA --backend onnx --models $OUT/onnx --start templates --candidates 5 --limit-images $N --threads 1 --templates-cache /work/data/tcache --no-progress --out $OUT/onnx_res --method onnx ) > onnx.log 2>&1
wait
echo done > DONE

#!/usr/bin/env bash
# Scratch: while a training runs, copy RUN/checkpoint.pt to RUN/snap_<step>.pt every EVERY seconds
# (train.py keeps one checkpoint; the held-out curve needs several) and score each copy on the 256
# held-out instances (niced, one thread) into bench/curves/2026-12-02-session6/heldout_<NAME>_<step>.json.
# Usage: snapshot_checkpoints.sh RUN NAME EVERY
run=$1; name=$2; every=${3:-720}
here=$(dirname "$0")
while pgrep -f "out $run" >/dev/null; do
  sleep "$every"
  pgrep -f "out $run" >/dev/null || break
  step=$(printf %05d "$(tail -1 "$run/log.jsonl" | python3 -c 'import json,sys; print(json.loads(sys.stdin.read())["step"])')")
  cp "$run/checkpoint.pt" "$run/snap.tmp" && mv "$run/snap.tmp" "$run/snap_$step.pt"
  OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python "$here/heldout_refiner.py" "$run/snap_$step.pt" \
    --out "$here/heldout_${name}_$step.json" > "$here/heldout_${name}_$step.log" 2>&1
done

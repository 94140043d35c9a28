#!/usr/bin/env bash
# AR of every CSV under the given folders (evaluated with the before tree's evaluator)
export PYTHONPATH=/tmp/base PYOPENGL_PLATFORM=egl OMP_WAIT_POLICY=PASSIVE
for d in "$@"; do for f in $(find $d -name "*.csv" | sort); do
  [ -f ${f%.csv}_eval/scores.json ] || /work/main/.venv/bin/python -m cosy_lite.cli eval --dataset /work/data/ycbvsynth --results $f --workers 1 --no-progress > ${f%.csv}.eval.log 2>&1
  echo "$f $(python3 -c "import json,sys; s=json.load(open('${f%.csv}_eval/scores.json')); print({k: round(v, 4) for k, v in s.items() if k.startswith('ar') or k.startswith('bop19')})" 2>&1 | tail -1)"
done; done

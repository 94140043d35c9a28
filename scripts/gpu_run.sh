#!/usr/bin/env bash
# The GPU run in one command (issue 18): scripts/gpu_run.sh OUT [--minutes M]       on the lent GPU machine
#                                        scripts/gpu_run.sh OUT --dry-run            anywhere, toy size, CPU (CI)
# On the GPU machine it runs under the image's python3 with the wheel bundle of scripts/gpu_bundle.py
# (.whl/, carried with the tree) installed into /tmp/site, and the GL loaders of .gl/ if carried.
# Device tool call: run(command="bash scripts/gpu_run.sh $OUT", carry=[".whl", ".gl"], timeout_s=600).
# Whatever happens, it ends within 9 minutes (the python side keeps to its budgets; timeout is the backstop).
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: scripts/gpu_run.sh OUT [--dry-run] [--minutes M]}
shift
export PYOPENGL_PLATFORM=egl PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
backstop=535  # s: the device call's 600 s minus the install and the hand-back
if [[ " $* " == *" --dry-run "* ]]; then
  py=${PYTHON:-.venv/bin/python}
  backstop=1800  # on a shared CPU the toy run took 535 s with tests and inference beside it (2026-12-04)
else
  if compgen -G ".gl/*.deb" >/dev/null; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
  fi
  nvidia_egl=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  [[ -f $nvidia_egl ]] && export __EGL_VENDOR_LIBRARY_FILENAMES=$nvidia_egl
  compgen -G ".whl/*.whl" >/dev/null || { echo "gpu_run: no wheels in .whl/ (run python scripts/gpu_bundle.py here and carry .whl)"; exit 2; }
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 2
  export PYTHONPATH=/tmp/site:$PWD
  py=python3
fi
timeout --signal=TERM --kill-after=10 "$backstop" "$py" scripts/gpu_run.py "$out" "$@"

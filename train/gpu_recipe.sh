#!/usr/bin/env bash
# The GPU recipe (`python -m mcdenoise gpu-recipe`, train/gpu_recipe.py): run by the device tool on a
# bare GPU machine, with `.gpu` carried (made by `python -m pipeline gpu-prepare --config
# configs/ship.yaml`). Installs the carried wheels next to the machine's torch, trains the shipped
# model further, times it, writes into $OUT. Arguments are gpu-recipe's flags (`--help`).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT="${OUT:-reports/gpu}"
MINUTES="${MINUTES:-6}"
python -m pip install --quiet --no-index --no-deps --target .gpu/site .gpu/wheels/*.whl
export PYTHONPATH="$PWD/.gpu/site:$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python -m mcdenoise gpu-recipe --out "$OUT" --minutes "$MINUTES" "$@"

#!/usr/bin/env bash
# The GPU recipe (tools/gpu/recipe.py): render, clean, train and time the shipped kind of model in one run.
# On a lent GPU machine, with `.gpu` carried (python tools/gpu/recipe.py prepare):  bash tools/gpu/recipe.sh
# On the CPU, in seconds:  DEVICE=cpu CONFIG=configs/tiny.yaml MINUTES=0.2 bash tools/gpu/recipe.sh
# Variables: CONFIG (configs/ship.yaml), MINUTES (9: the whole run), OUT (reports/gpu), DEVICE (auto),
# WORK (where the store and runs go); arguments are run's flags (python tools/gpu/recipe.py run --help).
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-reports/gpu}"
PY="${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}"
if [ -f .gpu/site.tar.xz ] && ! "$PY" -c "import mitsuba" 2>/dev/null; then
    SITE="${TMPDIR:-/tmp}/mcdenoise_site"
    mkdir -p "$SITE" && tar -xJf .gpu/site.tar.xz -C "$SITE"
    export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
fi
[ -d .gpu/oidn ] && export MCDENOISE_OIDN_WEIGHTS="${MCDENOISE_OIDN_WEIGHTS:-$PWD/.gpu/oidn}"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
exec "$PY" tools/gpu/recipe.py run --config "${CONFIG:-configs/ship.yaml}" --out "$OUT" --minutes "${MINUTES:-9}" \
    --device "${DEVICE:-auto}" ${WORK:+--work "$WORK"} "$@"

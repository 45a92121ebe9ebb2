#!/bin/bash
# usage: ft_select.sh OUT RUNS SETS [extra overrides] -- scores oidn and oidn_ft of RUNS on validation sets (default,ext)
set -e
OUT=$1; RUNS=$2; SETS=$3; shift 3
PY=${PY:-.venv/bin/python}
M='eval.methods=[oidn, oidn_ft]'
C=('eval.equal_time_methods=[]' 'eval.metrics=[l1, psnr, flip, hdr_flip]' eval.stress=false)
cd "$(dirname "$0")/../.."
if [[ $SETS == *default* ]]; then
$PY -m pipeline eval --config configs/default.yaml store=${DEFAULT_STORE:-data/default} runs=$RUNS eval.split=val "$M" "${C[@]}" eval.out=$OUT/default_val "$@" --quiet
fi
if [[ $SETS == *ext* ]]; then
S=(); for f in configs/scenes/val_*.xml; do S+=(--scene "$f"); done   # eval renders any the store lacks
$PY -m pipeline eval --config configs/default.yaml store=data/external runs=$RUNS dataset.gt_spp=4096 "$M" "${C[@]}" eval.out=$OUT/ext_val "$@" --quiet "${S[@]}"
fi

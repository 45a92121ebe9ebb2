#!/bin/bash
# usage: val_select.sh OUT RUNS SETS [extra overrides]  -- scores oidn and ours of RUNS on validation sets
# SETS: any of ship,default,ext (comma-separated)
set -e
OUT=$1; RUNS=$2; SETS=$3; shift 3
PY=/work/main/.venv/bin/python
M='eval.methods=[oidn, ours]'
C=('eval.equal_time_methods=[]' 'eval.metrics=[l1, psnr, flip, hdr_flip]' eval.stress=false)
cd /work/main
if [[ $SETS == *ship* ]]; then   # the ship config's own val split
$PY -m pipeline eval --config configs/ship.yaml store=data/ship runs=$RUNS eval.split=val "$M" "${C[@]}" eval.out=$OUT/ship_val "$@" --quiet
fi
if [[ $SETS == *default* ]]; then   # the default config's 8 val frames (other seed, other scenes)
$PY -m pipeline eval --config configs/default.yaml store=/tmp/fresh_demo3/data/default runs=$RUNS eval.split=val "$M" "${C[@]}" eval.out=$OUT/default_val "$@" --quiet
fi
if [[ $SETS == *ext* ]]; then   # the three hand-made val_* scenes (never trained on), GT1 at 4096 spp
$PY -m pipeline eval --config configs/default.yaml store=data/external runs=$RUNS dataset.gt_spp=4096 "$M" "${C[@]}" eval.out=$OUT/ext_val "$@" --quiet \
  --scene configs/scenes/val_glossy_corridor.xml --scene configs/scenes/val_hidden_light.xml --scene configs/scenes/val_shaderballs.xml
fi

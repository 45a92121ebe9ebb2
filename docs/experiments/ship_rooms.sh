#!/usr/bin/env bash
# docs/experiments/ship_rooms.md from the store to the scored candidates, and docs/sequences.md's model that
# reads the past on the same store: every step resumes where a killed run stopped (the render and the training
# resume; a step whose output exists is skipped), so the script is run again until it prints "all scored".
#
#   bash docs/experiments/ship_rooms.sh            # from the repository root, after `make setup`
#
# Needs data/external with the val_* scenes (render-scene configs/scenes/val_*.xml --config configs/default.yaml
# --store data/external dataset.gt_spp=4096), data/default (make dataset) and data/val_seq (docs/sequences.md).
# Scores land in docs/experiments/ship_rooms/*.txt; the rules that read them are in the two pages.
set -euo pipefail
PY=.venv/bin/python
C=configs/ship_rooms.yaml
OUT=docs/experiments/ship_rooms
mkdir -p "$OUT"

make dataset CONFIG=$C                                      # the rest of the render, then gt-clean

# 1 or 8 frames per scene: two training sets of equal cost, cut from the finished store
[ -d data/ship_rooms_1pf ] || $PY docs/experiments/subset_store.py data/ship_rooms data/ship_rooms_1pf --frames-per-scene 1
[ -d data/ship_rooms_8pf ] || $PY docs/experiments/subset_store.py data/ship_rooms data/ship_rooms_8pf \
  --frames-per-scene 8 --like data/ship_rooms_1pf
for s in 1pf 8pf; do
  make train CONFIG=$C SPP=any store=data/ship_rooms_$s runs=runs/ship_rooms_$s diffusion.init=train/shipped \
    diffusion.time_budget_s=0
done

# the candidates of the rule: warm-started from train/shipped, and from scratch, on the whole store; named
# variants of one runs folder, so that the two read one training pack (built once, most of an hour)
make train CONFIG=$C SPP=any diffusion.name=warm diffusion.init=train/shipped
make train CONFIG=$C SPP=any diffusion.name=scratch

# scored as the rule says: every noise realization, val_* at 4 spp, default val at 4 spp (train/shipped too);
# diffusion.model names the candidate (a run trained on another store than the scored one is otherwise passed over)
score() {   # score NAME MODEL
  local f
  for f in val default_val; do
    [ -s "$OUT/$1_$f.txt" ] && continue
    if [ $f = val ]; then where="--store data/external --prefix ext_val"; else where="--store data/default --split val --prefix="; fi
    $PY docs/oidn_guards/realizations.py --reference oidn_prefilter --methods ours $where --spp 4 \
      --json "$OUT/$1_$f.json" -- diffusion.model="$2" > "$OUT/$1_$f.txt.tmp"
    mv "$OUT/$1_$f.txt.tmp" "$OUT/$1_$f.txt"
  done
}
score shipped train/shipped
for r in 1pf 8pf; do score $r runs/ship_rooms_$r/diffusion_sppany; done
for r in warm scratch; do score $r runs/ship_rooms/diffusion_sppany_$r; done

# the model that reads the past (docs/sequences.md, "The same on configs/ship_rooms.yaml"): warm-started from
# train/shipped here; if the rule above ships a candidate, start from it instead (diffusion.init=<its folder>)
make train CONFIG=$C SPP=any diffusion.history=true diffusion.name=history diffusion.init=train/shipped
# ours_temporal is the history run's model reading its own output; ours_filter the filter on train/shipped
seqeval() {   # seqeval STORE NAME METHOD OVERRIDES...
  local store=$1 name=$2 method=$3; shift 3
  [ -s "$OUT/${name}_$(basename "$store").txt" ] || { $PY -m pipeline eval --config configs/sequence.yaml \
    store="$store" eval.split=val "eval.spp=[4,16]" "eval.methods=[oidn_prefilter]" eval.equal_time=none \
    eval.stress=false "eval.metrics=[l1, psnr]" "eval.sequence_methods=[oidn_prefilter, $method]" "$@" \
    --out "reports/ship_rooms_${name}_$(basename "$store")" > "$OUT/${name}_$(basename "$store").txt.tmp" \
    && mv "$OUT/${name}_$(basename "$store").txt.tmp" "$OUT/${name}_$(basename "$store").txt"; }
}
for store in data/sequence data/val_seq; do
  seqeval $store history ours_temporal diffusion.model=runs/ship_rooms/diffusion_sppany_history
  seqeval $store filter ours_filter diffusion.model=train/shipped
done
echo "all scored: $OUT"

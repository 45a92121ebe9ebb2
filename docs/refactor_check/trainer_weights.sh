#!/usr/bin/env bash
# Tiny runs of every trainer on configs/tiny.yaml, then a sha256 of every weights file they wrote
# (hash_weights.py: the tensors, not the metadata, whose history holds wall-clock seconds): run it at
# two commits (e.g. before and after a refactor) and compare the two listings. The weights must be
# identical (one torch thread; every random draw is seeded). Usage, from a checkout:
#     bash docs/refactor_check/trainer_weights.sh OUT_DIR > hashes.txt
set -euo pipefail
OUT=${1:?usage: trainer_weights.sh OUT_DIR}
PY=${PY:-.venv/bin/python}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
K=(--config configs/tiny.yaml "store=$OUT/store" "runs=$OUT/runs" --quiet)
CLEAN=(clean.epochs=2 clean.batch_size=4 clean.crop=16 clean.crops_per_frame=4 "clean.channels=[8, 8]"
       clean.embed_channels=8 clean.affinity_channels=4 clean.kernel_size=3 "clean.dilations=[1, 2]" clean.device=cpu)
AFGSA=(afgsa.epochs=2 afgsa.crop=16 afgsa.batch_size=2 afgsa.channels=8 afgsa.extractor_channels=4 afgsa.blocks=1
       afgsa.heads=2 afgsa.block_size=4 afgsa.halo=1 afgsa.critic_channels=4 afgsa.critic_levels=2 afgsa.device=cpu)
DIFF=("pretrain.channels=[16,32]" pretrain.crop=16 pretrain.epochs=1 diffusion.crop=16 diffusion.batch_size=2
      diffusion.val_skip=24 diffusion.val_frames=1 diffusion.epochs=2 diffusion.device=cpu)
FT=(oidn_ft.epochs=2 oidn_ft.crop=16 oidn_ft.batch_size=2 oidn_ft.crops_per_frame=2 oidn_ft.warmup_steps=1
    oidn_ft.lr=1e-3 oidn_ft.device=cpu oidn_ft.distill=0.5 oidn_ft.l2sp=0.1)
REF=(diffusion.epochs=2 diffusion.crop=16 diffusion.batch_size=2 diffusion.warmup_steps=1 diffusion.lr=1e-3
     diffusion.device=cpu diffusion.val_frames=1)

run() { "$PY" -m pipeline "$@" >/dev/null; }
run dataset "${K[@]}"
run gt-clean "${K[@]}" "${CLEAN[@]}"                                          # the cleaner
run train --model isik --spp any "${K[@]}" "${CLEAN[@]}"                      # the Isik baseline
run train --model afgsa --spp 4 "${K[@]}" "${AFGSA[@]}"                       # AFGSA
run pretrain "${K[@]}" "${DIFF[@]}" diffusion.estimate=oidn                   # the stand-in base
run train --model diffusion --spp any "${K[@]}" "${DIFF[@]}" diffusion.estimate=oidn \
    diffusion.train_base=false "diffusion.base=$OUT/runs/base"                  # Control Module, frozen stand-in
run train --model diffusion --spp 4 "${K[@]}" "${DIFF[@]}" diffusion.name=new  # refine default: new base + isik
run train --model oidn_ft --spp any "${K[@]}" "${FT[@]}"                      # OIDN fine-tuned
run train --model diffusion --spp any "${K[@]}" "${REF[@]}" diffusion.base=oidn diffusion.name=oidn  # on OIDN
"$PY" "$(dirname "$0")/hash_weights.py" "$OUT/runs"

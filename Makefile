# mcdenoise: Monte Carlo denoising dataset -> GT cleaner -> diffusion denoiser -> evaluation.
#
#   make demo                 the main job on configs/default.yaml: dataset, GT cleaning, the Isik,
#                             OIDN fine-tuned and AFGSA baselines (SPP=any), evaluation of every method with
#                             the shipped diffusion denoiser at 4, 16 and 64 spp (sets itself up)
#   make test                 lint (ruff: pycodestyle errors, pyflakes, import order) and the
#                             whole test suite, what CI runs (sets itself up)
#   make test-fast            lint and the unit tests (not marked slow): under 2 minutes on 2 cores
#   make train [SPP=4|any] [MODEL=...]  the shipped model's architecture and recipe on CONFIG's data
#   make dataset [CONFIG=...] [key=value ...]
#
# Any `key=value` on the command line that is not one of the Make variables below is passed to
# the pipeline as a config override, e.g. `make dataset dataset.scenes=4 render.max_depth=6`.

PYTHON_SYS ?= python3
VENV       ?= .venv
PY         := $(VENV)/bin/python
CONFIG     ?= configs/default.yaml
SPP        ?= 4
MODEL      ?= diffusion
SHARD      ?=
STAMP      := $(VENV)/.installed
# pytest-xdist processes of make test (the tests are single-threaded mostly): 19 min in one, 13 in two on 2 cores
TEST_WORKERS ?= 2

MAKE_VARS  := CONFIG SPP SHARD VENV PYTHON_SYS MODEL SCENES DEFINES TEST_WORKERS
# Words without '=' are the rest of a multi-word variable (SCENES="a.xml b.xml"), not overrides; nor are
# the scene parameters of DEFINES="spp=64 res=256" (its words after the first).
OVERRIDES  := $(strip $(filter-out $(DEFINES),$(foreach a,$(MAKEOVERRIDES),$(if $(findstring =,$(a)),$(if $(filter $(MAKE_VARS),$(firstword $(subst =, ,$(a)))),,$(a))))))
RUN        := $(PY) -m pipeline

.PHONY: help setup llvm demo dataset render gt-clean clean-report train eval stability inspect verify plan bench contact-sheet test test-fast clean distclean

help:
	@sed -n '1,13p' Makefile

# ---- set-up -------------------------------------------------------------------------------
setup: $(STAMP) llvm

# A virtual environment with the exact versions of requirements.lock, then the project itself
# without re-resolving (--no-deps): a looser resolve would pull CUDA builds of torch.
$(STAMP): requirements.lock pyproject.toml
	$(PYTHON_SYS) -m venv $(VENV)
	$(VENV)/bin/pip install --disable-pip-version-check -q --no-deps -r requirements.lock
	$(VENV)/bin/pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e .
	@touch $@

# Mitsuba's LLVM variants need libLLVM >= 16 (14/15 abort on the first render).
llvm:
	@if $(PYTHON_SYS) -c "import sys; sys.path.insert(0, '.'); from mcdenoise.pipeline.mitsuba_env import find_libllvm; sys.exit(0 if find_libllvm() else 1)"; then \
		true; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		echo "installing libllvm19 (Mitsuba's LLVM backend needs LLVM >= 16)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null; \
	else \
		echo "Mitsuba needs libLLVM >= 16. Install it (Debian/Ubuntu: sudo apt-get install libllvm19)"; \
		echo "or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version 16 or newer."; exit 1; \
	fi

# ---- stages -------------------------------------------------------------------------------
# The diffusion denoiser of the demo is the one shipped in train/shipped (trained on configs/ship.yaml,
# none of this config's scenes); `make train SPP=any` trains one on this config's data instead.
demo: setup
	$(MAKE) dataset CONFIG=$(CONFIG)
	$(RUN) inspect $$($(RUN) config --config $(CONFIG) $(OVERRIDES) | sed -n 's/^store: //p')
	$(RUN) train --model isik --spp any --config $(CONFIG) $(OVERRIDES)
	$(RUN) train --model oidn_ft --spp any --config $(CONFIG) $(OVERRIDES)
	$(RUN) train --model afgsa --spp any --config $(CONFIG) $(OVERRIDES)
	$(RUN) clean-report --config $(CONFIG) --spp $(SPP) $(OVERRIDES)
	$(RUN) eval --config $(CONFIG) $(OVERRIDES)

# `make dataset` renders, then cleans the ground truth (the cleaner trains on the whole train
# split, so with SHARD= only the rendering runs; run `make gt-clean` once all shards are done).
dataset: render
	$(if $(SHARD),@echo "shard $(SHARD) rendered; run 'make gt-clean' after the last shard",$(RUN) gt-clean --config $(CONFIG) $(OVERRIDES))

render: setup
	$(RUN) dataset --config $(CONFIG) $(if $(SHARD),--shard $(SHARD)) $(OVERRIDES)

gt-clean: setup
	$(RUN) gt-clean --config $(CONFIG) $(OVERRIDES)

# GT1 vs GT_clean against GT2, crop grid; with SPP= also the Isik baseline (after make train).
clean-report: setup
	$(RUN) clean-report --config $(CONFIG) $(if $(filter command line,$(origin SPP)),--spp $(SPP)) $(OVERRIDES)

# `make train SPP=4` trains the shipped model's architecture with its recipe (the diffusion.* defaults): a
# Control Module on OIDN's frozen final-frame network, into <runs>/diffusion_spp4 (train/train.py). MODEL=isik:
# the Isik baseline; MODEL=afgsa: AFGSA; MODEL=oidn_ft SPP=any: OIDN's network fine-tuned from its own weights.
# SPP=any trains one model for every sample count (diffusion_sppany, isik_sppany, afgsa_sppany; make eval uses
# them at every spp without a run of their own, and says which weights each row ran).
# `make train CONFIG=configs/ship.yaml SPP=any` trains train/shipped's recipe on its data again.
# Several GPUs/nodes: run the same command under `torchrun --nproc_per_node N -m pipeline train ...` (DDP).
train: setup
	$(RUN) train --model $(MODEL) --spp $(SPP) --config $(CONFIG) $(OVERRIDES)

# Every method on the test split per spp (eval.spp: 4, 16, 64) with 95 % intervals and paired
# bootstrap differences, the stress presets and external scenes as their own groups: tables, error
# vs time, crops in reports/<run>/. SPP=4 limits it to one sample count; SCENES="a.xml b.xml"
# renders Mitsuba 3 scenes into the store (split 'external') first and reports them separately;
# DEFINES="spp=64 res=256" gives their scene parameters ($spp, $res; Mitsuba's -D).
eval: setup
	$(RUN) eval --config $(CONFIG) $(OVERRIDES) $(if $(filter command line,$(origin SPP)),--spp $(SPP)) $(foreach s,$(SCENES),--scene $(s)) $(foreach d,$(DEFINES),-D $(d))

# Every method on synthetic edge cases (fireflies, NaN/Inf, black, 1e5, sizes up to 1920x1080).
stability: setup
	$(RUN) stability --config $(CONFIG) $(OVERRIDES)

inspect: setup
	$(RUN) inspect $$($(RUN) config --config $(CONFIG) $(OVERRIDES) | sed -n 's/^store: //p')

# Check every file of the store (channels, shapes, checksums, manifests, gt_clean hashes); exit 1 on problems.
verify: setup
	$(RUN) verify $$($(RUN) config --config $(CONFIG) $(OVERRIDES) | sed -n 's/^store: //p')

# What the dataset of CONFIG costs (core-hours, disk, wall time per core count), before running it.
plan: setup
	$(RUN) plan --config $(CONFIG) $(OVERRIDES)

bench: setup
	$(RUN) bench --config $(CONFIG) $(OVERRIDES)
	$(RUN) bench-denoise --config $(CONFIG) --spp $(SPP) $(OVERRIDES)

# A grid of random interiors, product shots and open sets with their render times (docs/scenes.md), ~12 min on 2 cores.
contact-sheet: setup
	$(PY) -m tools.contact_sheet --out docs/figures/scenes.png

# ---- tests --------------------------------------------------------------------------------
test: setup
	$(PY) -m ruff check .
	$(PY) -m pytest -q -n $(TEST_WORKERS) tests

test-fast: setup
	$(PY) -m ruff check .
	$(PY) -m pytest -q -n $(TEST_WORKERS) -m "not slow" tests

# ---- housekeeping (make clean deletes outputs; it is not the GT cleaner) -------------------
clean:
	rm -rf data runs reports .pytest_cache .ruff_cache

distclean: clean
	rm -rf $(VENV) *.egg-info

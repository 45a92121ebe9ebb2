"""Probe: oidn_ft on OIDN's large clean-aux network, the aux prefiltered (per 4-spp stack for training, as
pooled for validation), through the shipped training loop (train.baselines.oidn_ft) with the demo's recipe; the
config's check of oidn_ft.network (which does not know the large network yet) is stepped past.

    python docs/oidn_guards/ft_large_probe.py store=<demo>/data/default runs=RUNS
"""
import dataclasses
import sys

import numpy as np

from mcdenoise.clean.fit import fit
from mcdenoise.pipeline.config import load_config
from mcdenoise.train import oidn
from mcdenoise.train.baselines import oidn_ft
from mcdenoise.train.model import unet_denoise

_init = oidn_ft.Frame.__init__


def frame_init(self, store, key, aux, target="gt_clean"):
    _init(self, store, key, aux, target)
    a, n = self.aux["albedo"].astype(np.float32), self.aux["normal"].astype(np.float32)
    for k in range(len(a)):
        a[k], n[k] = oidn.prefilter_aux(np.clip(a[k], 0, 1), np.clip(n[k], -1, 1))
    self.aux = {"albedo": a.astype(np.float16), "normal": n.astype(np.float16)}


def val_items(self):
    items = _val(self)
    for it in items:
        c, a, n = it["images"]
        a, n = oidn.prefilter_aux(np.clip(a, 0, 1), np.clip(n, -1, 1))
        it["images"] = [c, a, n]
        it["stock"] = unet_denoise(self.teacher, c, a, n, device=self.device)
    return items


_val = oidn_ft.OIDNFineTune._validation_items
oidn_ft.Frame.__init__ = frame_init
oidn_ft.OIDNFineTune._validation_items = val_items
cfg = load_config("configs/default.yaml", sys.argv[1:])
cfg = dataclasses.replace(cfg, oidn_ft=dataclasses.replace(cfg.oidn_ft, network="rt_hdr_calb_cnrm_large"))  # past the config check
print(fit(oidn_ft.OIDNFineTune(cfg, "any")))

"""The RMS gradient of every layer of OIDN's network on the default config's training crops, at OIDN's
weights (the first step of oidn_ft), beside the RMS weight: python docs/oidn_guards/fine/grad_scale.py"""
import numpy as np
import torch
import torch.nn.functional as F

from mcdenoise.pipeline.config import load_config
from mcdenoise.train.baselines.oidn_ft import OIDNFineTune
from mcdenoise.train.model import LEVEL

BATCHES = 16

torch.set_num_threads(1)
task = OIDNFineTune(load_config("configs/default.yaml", ["oidn_ft.trainable=all"]), "any")
task.prepare()
squares = {n: 0.0 for n, _ in task.net.named_parameters()}
for i, batch in enumerate(task.batches(0)):
    if i == BATCHES:
        break
    task.net.zero_grad()
    F.l1_loss(task.net(batch["input"]), batch["target"]).backward()
    for n, p in task.net.named_parameters():
        squares[n] += p.grad.pow(2).mean().item()
print("| layer | level | RMS gradient | RMS weight |\n| --- | --- | --- | --- |")
for n, p in task.net.named_parameters():
    if n.endswith(".weight"):
        layer = n.split(".")[0]
        print(f"| {layer} | {LEVEL[layer]} | {np.sqrt(squares[n] / BATCHES):.1e} | "
              f"{p.detach().pow(2).mean().sqrt().item():.2f} |")

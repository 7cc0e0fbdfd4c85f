"""Fingerprint of today's loss (4-step items, one-step targets) for the sequence-replay test."""

import json

import torch

from icco_torchrl.training.build import build_components
from icco_torchrl.training.segments import SegmentCutter

torch.set_num_threads(1)
out_all = {}
for method in ["icco", "qmix_full"]:
    torch.manual_seed(0)
    parts = build_components(method=method, num_envs=8)
    torch.manual_seed(0)
    parts["env"].set_seed(0)
    with torch.no_grad():
        ro = parts["env"].rollout(24, parts["policy"], break_when_any_done=False)
    seg = SegmentCutter(length=4)(ro)
    loss = parts["loss"]
    torch.manual_seed(123)
    out = loss(seg)
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    total.backward()
    g = torch.Generator().manual_seed(7)
    grads = {}
    for name, p in sorted(loss.named_parameters()):
        if p.grad is None:
            continue
        proj = torch.randn(p.grad.numel(), generator=g, dtype=torch.float64)
        grads[name] = [
            p.grad.double().sum().item(),
            p.grad.double().norm().item(),
            (p.grad.double().flatten() @ proj).item(),
        ]
    out_all[method] = {
        "losses": {k: v.item() for k, v in out.items()},
        "grads": grads,
        "segments": seg.shape[0],
    }
json.dump(out_all, open("/tmp/loss_reference.json", "w"), indent=1)
print(
    {m: v["losses"] for m, v in out_all.items()}, {m: len(v["grads"]) for m, v in out_all.items()}
)

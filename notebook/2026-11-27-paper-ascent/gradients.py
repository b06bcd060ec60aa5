"""Difference gradients of the exact psi against autograd on the plant (float64), by step.

Ran at commit 6a84c7c from the repository root: ``python gradients.py``. The map, pool and
Hhat of ``agilegs bench latency --scene service/data/scenes/plant --max-gaussians 20000
--width 128 --height 128 --pool 200``; psi at 64^2; three pool poses.
"""

import argparse
import sys

import torch

from agilegs.config.selection import FIELD_NAMES, AnchorConfig
from agilegs.service.bench import latency
from agilegs.service.bench.options import add_latency_arguments
from agilegs.service.nbv.anchor.ascent import _exp_at_zero
from agilegs.service.nbv.anchor.envelope import PoolEnvelope
from agilegs.service.nbv.anchor.exact import ExactPsi

parser = argparse.ArgumentParser()
add_latency_arguments(parser)
args = parser.parse_args(["--scene", "service/data/scenes/plant", "--max-gaussians", "20000",
                          "--width", "128", "--height", "128", "--pool", "200", "--threads", "1"])
torch.set_num_threads(1)
setup = latency.set_up(args, torch.device("cpu"))
gmap = setup.gmap.to(dtype=torch.float64)
h_acc = {k: v.double() for k, v in setup.h_acc.items()}
pool = setup.pool.double()
cfg = AnchorConfig(psi="exact")
env = PoolEnvelope.from_pool(pool, gmap.means.median(0).values)
ref = ExactPsi(gmap, h_acc, setup.intrinsics, cfg, FIELD_NAMES, gradient="autograd")
poses = env.project(pool[10:13])
xi = torch.zeros(poses.shape[0], 6, dtype=poses.dtype, requires_grad=True)
(auto,) = torch.autograd.grad(ref(env.project(poses @ _exp_at_zero(xi))).sum(), xi)
metric = torch.tensor([env.radius] * 3 + [1.0] * 3, dtype=torch.float64)
with torch.no_grad():
    center = ref(poses)
for mode in ("central", "forward"):
    for step in (1e-7, 1e-6, 1e-5, 1e-4, 1e-3):
        psi = ExactPsi(gmap, h_acc, setup.intrinsics, cfg, FIELD_NAMES, gradient=mode,  # type: ignore[arg-type]
                       step=step)
        _, diff = psi.twist_gradient(poses, envelope=env, radius=env.radius, center=center)
        a, d = auto * metric, diff * metric
        cos = torch.nn.functional.cosine_similarity(a, d, dim=1)
        rel = (a - d).norm(dim=1) / a.norm(dim=1)
        sys.stdout.write(f"{mode} {step:g} cos {[round(x, 3) for x in cos.tolist()]} "
                         f"rel {[round(x, 3) for x in rel.tolist()]}\n")

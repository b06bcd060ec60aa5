"""Per-event stage times of AGILE-GS with and without the anchor's parts carried over.

Ran at commit 278cf8c (which added ``AnchorConfig.carry_over_tolerance``), from the root:
``python carry_over.py``. ``bench latency``'s setup (the plant, 20k Gaussians, 128², pool 200,
5 acquired views, one thread); the events acquire the full-pool EIG's picks of that benchmark
(185, 168, 96), then three more selections repeat the last event without an acquisition.
"""

import argparse
import sys

import torch

from agilegs.config.selection import AnchorConfig, SelectConfig
from agilegs.service.bench import latency
from agilegs.service.bench.options import add_latency_arguments
from agilegs.service.nbv import Camera, accumulate_information, eig_scores, fisher_diag, select

parser = argparse.ArgumentParser()
add_latency_arguments(parser)
args = parser.parse_args(["--scene", "service/data/scenes/plant", "--max-gaussians", "20000",
                          "--width", "128", "--height", "128", "--pool", "200", "--threads", "1"])
torch.set_num_threads(1)
s = latency.set_up(args, torch.device("cpu"))
configs = {tol: SelectConfig(seed=args.seed, anchor=AnchorConfig(carry_over_tolerance=tol))
           for tol in (0.0, 0.2)}
states: dict[float, dict | None] = {tol: None for tol in configs}
h, pool, acquired = s.h_acc, s.pool, s.acquired
stages = ("anchor", "anchor.visibility", "anchor.rates", "anchor.unexplored", "anchor.starts",
          "anchor.ascent")
for event, nxt in enumerate([185, 168, 96, None, None, None]):
    phi = eig_scores(s.gmap, h, pool, s.intrinsics)
    for tol, cfg in configs.items():
        sel = select("agile", s.gmap, h, pool, s.intrinsics, config=cfg, acquired=acquired,
                     state=states[tol])
        states[tol] = sel.state
        pct = float((phi < phi[sel.index]).double().mean() * 100)
        times = " ".join(f"{k.split('.')[-1]} {sel.latency_ms.get(k, 0.0):.1f}" for k in stages)
        sys.stdout.write(f"event {event} tol {tol}: total {sel.latency_ms['total']:.1f} {times}"
                         f" carried {sel.details.get('anchor_carried')} pick {sel.index}"
                         f" pct {pct:.1f}\n")
    if nxt is not None:
        with torch.no_grad():
            hv = fisher_diag(s.gmap, Camera(c2w=pool[nxt], intrinsics=s.intrinsics))
        h = accumulate_information(h, hv)
        acquired = torch.cat([acquired, pool[nxt:nxt + 1]])
        pool = torch.cat([pool[:nxt], pool[nxt + 1:]])

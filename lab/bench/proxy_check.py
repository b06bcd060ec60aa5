"""``agilegs bench proxy``: how well the anchor's choices follow the exact EIG on trained maps.

The progressive protocol (``bench run``) is driven by one method (``--driver``, Random by
default, so that every configuration sees the same maps); before each of its selections,
Hhat is formed from the acquired views on the current map, the exact phi of every remaining
candidate is computed (``full_eig``'s scores), and each anchor configuration selects on the same
inputs. Reported per configuration, per event and as means over all events and scenes:

- ``spearman``: rank correlation of the proxy psi of every remaining candidate with phi;
- ``agile_pct``: percentile of AGILE-GS's pick (the shortlist's first) within phi;
- ``plus_pct``: that of the shortlist's best view under phi (AGILE-GS+'s pick);
- ``agile_sep_deg`` / ``plus_sep_deg``: the angle, seen from the map centre, between that
  view and the nearest acquired view (small: a near-duplicate of what is held).

Configurations are ``default`` (the defaults) or variant options of ``agile``
(:mod:`agilegs.lab.bench.variants`), joined by ``+`` to combine them: for example
``typical``, ``unconditioned``, ``typical+unconditioned``, ``point_zbuffer``. Each keeps its
own warm-start state along the run.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from agilegs.service.nbv import information_of_views, select
from agilegs.service.nbv.candidates import scene_center_radius

from .latency import eig_percentile, spearman
from .options import DEFAULT_CONFIGS, protocol_profile
from .options import add_proxy_arguments as add_arguments
from .protocol import run_progressive
from .scenes import load_bench_scene
from .variants import Variant, parse_variant

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_CONFIGS", "add_arguments", "config_variant", "percentile", "run", "spearman"]


def config_variant(name: str) -> Variant:
    """The ``agile`` variant a configuration name stands for (``default``: the defaults)."""
    return parse_variant("agile" if name == "default" else f"agile@{name}")


METRICS = ("spearman", "agile_pct", "plus_pct", "agile_sep_deg", "plus_sep_deg")


def percentile(phi: Tensor, v: int) -> float:
    """Percentage of candidates whose phi is at or below candidate ``v``'s (100: the best;
    the same definition as ``bench latency``'s EIG percentile)."""
    return eig_percentile(phi, float(phi[v]))


def separation_deg(view: Tensor, acquired: Tensor, centre: Tensor) -> float:
    """Smallest angle (degrees, seen from ``centre``) between a pose [4, 4] and poses [A, 4, 4]."""
    d = view[:3, 3] - centre
    d = d / d.norm().clamp_min(1e-12)
    a = acquired[:, :3, 3] - centre
    a = a / a.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return float(torch.rad2deg(torch.acos((a @ d).clamp(-1, 1))).min())


def check_event(
    ctx: dict[str, Any], configs: dict[str, Variant], states: dict[str, Any], lam: float
) -> dict[str, dict[str, float]]:
    """Every configuration's figures on one event's inputs (see the module docstring)."""
    gmap, cands, acq = ctx["gmap"], ctx["candidates"], ctx["acquired"]
    intr, cfg0 = ctx["intrinsics"], ctx["config"]
    h_acc = information_of_views(gmap, acq, intr, lam, ctx["background"])
    fr = select("full_eig", gmap, h_acc, cands, intr, config=cfg0, acquired=acq, lam=lam)
    phi = torch.tensor([fr.scores[i] for i in range(cands.shape[0])], dtype=torch.float64)
    centre, _ = scene_center_radius(gmap.means.detach())
    out: dict[str, dict[str, float]] = {}
    for name, variant in configs.items():
        sel = select(variant.method, gmap, h_acc, cands, intr, config=variant.config(cfg0),
                     acquired=acq, state=states.get(name), lam=lam)
        states[name] = sel.state
        pool_psi = sel.details.get("pool_proxy_psi") or {}
        psi = torch.tensor([pool_psi.get(i, float("nan")) for i in range(len(phi))],
                           dtype=torch.float64)
        best = max(sel.shortlist, key=lambda v: float(phi[v]))
        out[name] = {
            "spearman": spearman(psi, phi) if bool(torch.isfinite(psi).all()) else float("nan"),
            "agile_pct": percentile(phi, sel.index),
            "plus_pct": percentile(phi, best),
            "agile_sep_deg": separation_deg(cands[sel.index], acq, centre),
            "plus_sep_deg": separation_deg(cands[best], acq, centre),
        }
    return out


def run(args: argparse.Namespace) -> int:
    names = [c.strip() for c in str(args.configs).split(",") if c.strip()]
    try:
        configs = {n: config_variant(n) for n in names}
        driver = parse_variant(args.driver)
    except ValueError as exc:
        raise SystemExit(f"--configs / --driver: {exc}") from None
    profile = protocol_profile(args)
    paths = list(args.scene)
    results: dict[str, Any] = {"profile": profile.name, "seed": args.seed,
                               "driver": args.driver, "scenes": {}}
    for path in paths:
        scene = load_bench_scene(path, profile.scene)
        events: list[dict[str, Any]] = []
        states: dict[str, Any] = {}

        def on_event(ctx: dict[str, Any], events: list[dict[str, Any]] = events,
                     states: dict[str, Any] = states, name: str = scene.name) -> None:
            figs = check_event(ctx, configs, states, profile.lam)
            events.append(figs)
            log.info("%s event %d: %s", name, ctx["event"], "  ".join(
                f"{n} rho {f['spearman']:+.2f} pick {f['agile_pct']:.0f}" for n, f in figs.items()))

        run_progressive(scene, driver, args.seed, profile, on_event=on_event)
        results["scenes"][scene.name] = events
    all_events = [e for evs in results["scenes"].values() for e in evs]
    means = {
        n: {m: statistics.fmean(e[n][m] for e in all_events) for m in METRICS}
        for n in configs
    }
    results["means"] = means
    results["events"] = len(all_events)
    lines = ["| configuration | proxy Spearman | AGILE-GS pick pct | shortlist best pct "
             "| pick sep. (deg) | best sep. (deg) |", "|---|---|---|---|---|---|"]
    for n, f in means.items():
        lines.append(f"| {n} | {f['spearman']:.2f} | {f['agile_pct']:.1f} | {f['plus_pct']:.1f} "
                     f"| {f['agile_sep_deg']:.1f} | {f['plus_sep_deg']:.1f} |")
    sys.stdout.write(f"{len(all_events)} events over {len(results['scenes'])} scenes, seed "
                     f"{args.seed}, driver {args.driver}:\n" + "\n".join(lines) + "\n")
    if args.json_out:
        Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json_out).write_text(json.dumps(results, indent=1))
    return 0

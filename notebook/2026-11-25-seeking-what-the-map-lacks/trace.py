"""Replay AGILE-GS's stages on snapshots of a progressive run: the measurement behind
../2026-11-25-seeking-what-the-map-lacks.md.

A lab script of the notebook, not maintained with the package: it imports the benchmark's
modules as they were at commit 0f47619. To run it again, check out that commit.

``snap`` runs the progressive protocol with one driver method and saves, at every
acquisition event, the map, Ĥ, the candidates, the acquired poses and the full-pool EIG of
every candidate. ``stages`` replays the selection of each variant on every saved event and
prints, as means over the events: the Spearman of the anchor's ψ over the pool with the
exact EIG, the EIG percentile of the pick and of the shortlist's best view, the angle from
the pick (and the shortlist) to the nearest acquired view, and the shortlist's spread
(mean pairwise angle), angles seen from the centre of the pool, in degrees.

    python notebook/2026-11-25-seeking-what-the-map-lacks/trace.py snap \
        service/data/scenes/boot --driver agile@single --seed 0 --out boot.pt
    python notebook/2026-11-25-seeking-what-the-map-lacks/trace.py stages \
        agile@single,agile@one_anchor,agile boot.pt
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np
import torch

from agilegs.service.bench.latency import eig_percentile, spearman
from agilegs.service.bench.profiles import resolve_profile
from agilegs.service.bench.protocol import run_progressive
from agilegs.service.bench.redundancy import angles_to_nearest, pool_directions
from agilegs.service.bench.scenes import load_bench_scene
from agilegs.service.bench.variants import parse_variant
from agilegs.service.nbv import GaussianMap, information_of_views, select
from agilegs.service.nbv.selectors import SelectConfig

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")
OVERRIDES = ("pool_size", "resolution", "max_gaussians", "initial_views", "interval", "steps",
             "view_budget", "shortlist_size", "lam")


def directions(poses: torch.Tensor, centre: torch.Tensor) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses -> (N, 3) unit directions of their centres."""
    return pool_directions(poses[:, :3, 3].double().numpy(), centre.double().numpy())


def spread(poses: torch.Tensor, centre: torch.Tensor) -> float:
    """Mean pairwise angle, in degrees, of (n, 4, 4) poses."""
    d = directions(poses, centre)
    n = d.shape[0]
    ang = np.degrees(np.arccos(np.clip(d @ d.T, -1.0, 1.0)))
    return float(ang[~np.eye(n, dtype=bool)].mean()) if n > 1 else 0.0


def snap(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    prof = resolve_profile(argparse.Namespace(profile=args.profile,
                                              **{k: None for k in OVERRIDES}))
    scene = load_bench_scene(args.scene, prof.scene)
    snaps: list[dict[str, Any]] = []

    def on_event(ctx: dict[str, Any]) -> None:
        gmap, cands, acq = ctx["gmap"], ctx["candidates"], ctx["acquired"]
        h = information_of_views(gmap, acq, ctx["intrinsics"], prof.lam, ctx["background"])
        full = select("full_eig", gmap, h, cands, ctx["intrinsics"], config=ctx["config"],
                      acquired=acq, lam=prof.lam)
        phi = torch.tensor([full.scores[i] for i in range(cands.shape[0])], dtype=torch.float64)
        snaps.append({
            "gmap": {k: getattr(gmap, k).detach().clone() for k in FIELDS},
            "h_acc": {k: v.clone() for k, v in h.items()}, "cands": cands.clone(),
            "acq": acq.clone(), "intr": ctx["intrinsics"], "phi": phi,
            "event": ctx["event"], "seed": int(ctx["config"].seed),
            "background": ctx["config"].fisher_background})
        sys.stdout.write(f"event {ctx['event']}\n")

    rec = run_progressive(scene, parse_variant(args.driver), args.seed, prof, on_event=on_event)
    torch.save({"snaps": snaps, "pool_poses": scene.pool_poses, "lam": prof.lam,
                "psnr": rec["psnr"]}, args.out)
    sys.stdout.write(f"{scene.name}: {rec['psnr']:.2f} dB, {len(snaps)} events -> {args.out}\n")


def stages(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    for path in args.snapshots:
        d = torch.load(path, weights_only=False)
        centre = d["pool_poses"][:, :3, 3].mean(0)
        sys.stdout.write(f"{path} (driver's PSNR {d['psnr']:.2f} dB)\n")
        for key in args.variants.split(","):
            variant, state, rows = parse_variant(key), None, []
            for s in d["snaps"]:
                base = SelectConfig(seed=s["seed"], fisher_background=s["background"])
                sel = select(variant.method, GaussianMap(**s["gmap"]), s["h_acc"], s["cands"],
                             s["intr"], config=variant.config(base), acquired=s["acq"],
                             state=state, lam=d["lam"])
                state = sel.state
                phi = s["phi"]
                ang = angles_to_nearest(directions(s["cands"], centre),
                                        directions(s["acq"], centre))
                best = max(sel.shortlist, key=lambda i: float(phi[i]))
                pool_psi = sel.details.get("pool_proxy_psi") or {}
                psi = torch.tensor([pool_psi.get(i, float("nan")) for i in range(len(phi))],
                                   dtype=torch.float64)
                rho = spearman(psi, phi) if bool(torch.isfinite(psi).all()) else float("nan")
                rows.append((rho, eig_percentile(phi, float(phi[sel.index])),
                             eig_percentile(phi, float(phi[best])), float(ang[sel.index]),
                             float(ang[sel.shortlist].mean()),
                             spread(s["cands"][sel.shortlist], centre)))
            m = [sum(r[j] for r in rows) / len(rows) for j in range(6)]
            sys.stdout.write(
                f"  {key:28s} Spearman {m[0]:+.2f}  pick pct {m[1]:5.1f}  shortlist best pct "
                f"{m[2]:5.1f}  pick angle {m[3]:5.1f}  shortlist angle {m[4]:5.1f}  "
                f"shortlist spread {m[5]:5.1f}\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("snap")
    s.add_argument("scene")
    s.add_argument("--driver", default="random")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--profile", default="cpu")
    s.add_argument("--out", required=True)
    t = sub.add_parser("stages")
    t.add_argument("variants")
    t.add_argument("snapshots", nargs="+")
    args = ap.parse_args()
    snap(args) if args.cmd == "snap" else stages(args)


if __name__ == "__main__":
    main()

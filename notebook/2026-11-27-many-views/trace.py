"""Where AGILE-GS's ψ parts from the exact EIG when the map is well covered: the measurement
behind ../2026-11-27-many-views.md.

A lab script of the notebook, not maintained with the package: it imports the benchmark's
modules as they are at the commit the note names.

``snap`` runs the progressive protocol with one driver method and saves, every ``--every``
events, the map, Ĥ, the candidates, the acquired poses and the full-pool EIG of every
candidate. ``parts`` rebuilds the default anchor's proxy on every snapshot and splits its ψ
over the pool into the map's Gaussians and the unexplored space, with the Spearman of each
with the exact EIG, the unexplored share of ψ, and where the unexplored points lie.

    python notebook/2026-11-27-many-views/trace.py snap service/data/scenes/bob \
        --profile cpu_long --every 5 --out bob.pt
    python notebook/2026-11-27-many-views/trace.py parts agile bob.pt
    python notebook/2026-11-27-many-views/trace.py parts agile --set transmittance_cells=32 bob.pt

Note: ``parts`` needs unexplored points to split ψ; its line shows only the pick's
percentile when the variant has none (``agile@no_unexplored``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import Any

import torch

from agilegs.service.bench.latency import eig_percentile, spearman
from agilegs.service.bench.profiles import resolve_profile
from agilegs.service.bench.protocol import run_progressive
from agilegs.service.bench.scenes import load_bench_scene
from agilegs.service.bench.variants import parse_variant
from agilegs.service.nbv import GaussianMap, information_of_views, select
from agilegs.service.nbv.anchor import proxy as proxy_mod
from agilegs.service.nbv.candidates import scene_center_radius
from agilegs.service.nbv.selectors import SelectConfig

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def snap(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    prof = resolve_profile(argparse.Namespace(profile=args.profile))
    scene = load_bench_scene(args.scene, prof.scene)
    snaps: list[dict[str, Any]] = []

    def on_event(ctx: dict[str, Any]) -> None:
        if ctx["event"] % args.every:
            return
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
        sys.stdout.flush()

    rec = run_progressive(scene, parse_variant(args.driver), args.seed, prof, on_event=on_event)
    torch.save({"snaps": snaps, "pool_poses": scene.pool_poses, "lam": prof.lam,
                "psnr": rec["psnr"]}, args.out)
    sys.stdout.write(f"{scene.name}: {rec['psnr']:.2f} dB, {len(snaps)} events -> {args.out}\n")


def parts(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    captured: list[tuple[Any, int]] = []
    orig = proxy_mod.ProxyPsi.extended

    def spy(self: Any, means: Any, cov: Any, weight: Any, rate: Any) -> Any:
        out = orig(self, means, cov, weight, rate)
        captured.append((out, int(self.means.shape[0])))
        return out

    proxy_mod.ProxyPsi.extended = spy  # type: ignore[method-assign]
    for path in args.snapshots:
        d = torch.load(path, weights_only=False)
        sys.stdout.write(f"{path} (driver's PSNR {d['psnr']:.2f} dB)\n")
        variant = parse_variant(args.variant)
        for s in d["snaps"]:
            captured.clear()
            base = SelectConfig(seed=s["seed"], fisher_background=s["background"])
            gmap = GaussianMap(**s["gmap"])
            cfg = variant.config(base)
            if args.set:
                over = {k: type(getattr(cfg.anchor, k))(v) for k, v in
                        (kv.split("=") for kv in args.set.split(","))}
                cfg = dataclasses.replace(cfg, anchor=dataclasses.replace(cfg.anchor, **over))
            sel = select(variant.method, gmap, s["h_acc"], s["cands"], s["intr"],
                         config=cfg, acquired=s["acq"], lam=d["lam"])
            phi = s["phi"]
            line = (f"  event {s['event']:2d}  views {s['acq'].shape[0]:2d}  pick pct "
                    f"{eig_percentile(phi, float(phi[sel.index])):5.1f}")
            if captured:
                prox, n_map = captured[-1]
                with torch.no_grad():
                    per = prox(s["cands"].to(prox.means.dtype), per_sample=True)
                psi_map, psi_un = per[:, :n_map].sum(1), per[:, n_map:].sum(1)
                total = psi_map + psi_un
                c, r = scene_center_radius(gmap.means.detach())
                um = prox.means[n_map:]
                dist = ((um - c).norm(dim=1) / r)
                line += (f"  rho total {spearman(total, phi):+.2f} "
                         f"map {spearman(psi_map, phi):+.2f} "
                         f"unexplored {spearman(psi_un, phi):+.2f}  unexplored share "
                         f"{float((psi_un / total).mean()):.2f}  points {um.shape[0]} "
                         f"(r/r98 median {float(dist.median()):.2f})  map-only pick pct "
                         f"{eig_percentile(phi, float(phi[int(torch.argmax(psi_map))])):5.1f}")
            sys.stdout.write(line + "\n")
            sys.stdout.flush()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("snap")
    s.add_argument("scene")
    s.add_argument("--driver", default="random")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--profile", default="cpu_long")
    s.add_argument("--every", type=int, default=5)
    s.add_argument("--out", required=True)
    t = sub.add_parser("parts")
    t.add_argument("variant")
    t.add_argument("--set", default="", help="anchor settings, k=v,k=v (ints and floats)")
    t.add_argument("snapshots", nargs="+")
    args = ap.parse_args()
    snap(args) if args.cmd == "snap" else parts(args)


if __name__ == "__main__":
    main()

"""``agilegs bench value``: what each candidate is worth, measured, and what predicts it.

The progressive protocol (:mod:`agilegs.lab.bench.protocol`) runs with one method driving
the acquisitions (``--driver``, Random by default). At the chosen events (``--events``),
before the driver selects:

1. **Scores.** On the current map, every remaining candidate is scored by everything the
   project computes: the exact EIG φ (as ``full_eig``), the trace surrogate ψ = Σ H_v / Ĥ,
   variants of the information model (λ, the parameter blocks that count, the background
   the Fisher is rendered on), FisherRF's score, COVER's coverage (negated: less covered
   scores higher), the anchor's proxy ψ (the default and the z-buffer visibility), and the
   shortlists of AGILE-GS and AGILE-GS+ (default and the paper's configuration) as scores
   (a member's score falls with its position, or rises with its φ; non-members tie below).
   Every method also makes its pick.
2. **Realised gains.** A sample of candidates (every method's pick, the default shortlist,
   and a seeded random fill up to ``--candidates``; the whole pool when it is smaller) is
   each given to a clone of the trainer (:meth:`Mapper.clone`: the same map, optimiser
   moments, statistics and generators), which then trains for ``--horizon`` steps (default:
   the profile's interval); the realised gain of a candidate is the test PSNR of that
   branch minus that of a branch trained the same steps without a new view. Two candidates
   differ only by the view.
3. **Agreement.** Per event, the Spearman rank correlation (ties averaged) of each score
   with the realised gain over the sample, and where each method's pick falls in the
   realised-gain ranking of the sample (percentile: 100 = the best candidate of the sample).

The driver's own run continues untouched (the branches are clones). Output: a JSON file
(``--json``) with every event's candidates, gains and scores, the per-scene and overall
means, a table on stdout, and a plot per scene (``--plots DIR``).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import statistics
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from agilegs.config.selection import FIELD_NAMES, SelectConfig
from agilegs.service.nbv import Camera, fisher_diag, select

from .options import add_value_arguments as add_arguments
from .options import protocol_profile
from .profiles import Profile
from .protocol import add_pool_view, evaluate, run_progressive
from .scene_model import BenchScene
from .scenes import load_bench_scene
from .variants import Variant, parse_variant

log = logging.getLogger(__name__)

__all__ = ["BLOCKS", "PICKS", "add_arguments", "rank_correlation", "run", "value_event"]

BLOCKS: dict[str, tuple[str, ...]] = {
    "all": FIELD_NAMES,
    "geometry": ("means", "log_scales", "quats"),
    "appearance": ("opacity_logits", "sh"),
    "no_sh": ("means", "log_scales", "quats", "opacity_logits"),
}
"""Parameter-block subsets of the information-model variants."""
LAMBDAS: tuple[float, ...] = (1e-6, 1e-3, 1e-1)
"""λ of the information-model variants (the profile's λ is among the defaults)."""
PICKS: tuple[str, ...] = ("random", "spread", "fisherrf", "cover", "full_eig", "agile",
                          "agile_plus", "agile@paper", "agile_plus@paper")
"""The methods whose picks are placed in the realised-gain ranking."""
SHORTLISTS: tuple[str, ...] = ("agile", "agile@paper", "agile@cover_zbuffer",
                               "agile@unconditioned")
"""Shortlist configurations scored by membership (their anchors' ψ too)."""


# ----------------------------------------------------------------------------- statistics
def average_ranks(x: Tensor) -> Tensor:
    """Ranks 0..n-1 of ``x`` [n], ties given their average rank (float64)."""
    x = x.to(torch.float64)
    order = torch.argsort(x, stable=True)
    ranks = torch.empty_like(x)
    ranks[order] = torch.arange(x.numel(), dtype=torch.float64)
    uniq, inv = torch.unique(x, return_inverse=True)
    sums = torch.zeros(uniq.numel(), dtype=torch.float64).index_add_(0, inv, ranks)
    counts = torch.zeros(uniq.numel(), dtype=torch.float64).index_add_(
        0, inv, torch.ones_like(ranks))
    return (sums / counts)[inv]


def rank_correlation(a: Sequence[float] | Tensor, b: Sequence[float] | Tensor) -> float:
    """Spearman's rank correlation of two score vectors, ties averaged (NaN when either is
    constant or they hold fewer than 3 values)."""
    ta = torch.as_tensor(a, dtype=torch.float64)
    tb = torch.as_tensor(b, dtype=torch.float64)
    if ta.numel() < 3 or ta.numel() != tb.numel():
        return float("nan")
    ra, rb = average_ranks(ta), average_ranks(tb)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    den = float(ra.norm() * rb.norm())
    return float((ra * rb).sum()) / den if den > 0 else float("nan")


def gain_percentile(gains: Sequence[float], value: float) -> float:
    """Percentage of the sample whose gain is at most ``value`` (100: the best)."""
    return 100.0 * sum(g <= value + 1e-12 for g in gains) / max(len(gains), 1)


# ----------------------------------------------------------------------------- scores
def _information_scores(
    gmap: Any, cands: Tensor, acquired: Tensor, intr: Any, bg: Tensor, lam: float,
) -> dict[str, list[float]]:
    """The information-model scores of every candidate: EIG and trace for each λ and block
    subset on the scene's background, and the EIG on black."""
    out: dict[str, list[float]] = {}
    for tag, background in (("", bg), ("black_bg", None)):
        with torch.no_grad():
            h_sum = {k: torch.zeros_like(v) for k, v in gmap.items()}
            for pose in acquired:
                hv = fisher_diag(gmap, Camera(c2w=pose, intrinsics=intr), background=background)
                for k in h_sum:
                    h_sum[k] += hv[k]
            lams = LAMBDAS if not tag else (lam,)
            blocks = BLOCKS if not tag else {"all": FIELD_NAMES}
            for pose in cands:
                hv = fisher_diag(gmap, Camera(c2w=pose, intrinsics=intr), background=background)
                for lv in sorted(set(lams) | {lam}):
                    for bname, fields in blocks.items():
                        eig = 0.0
                        tr = 0.0
                        for f in fields:
                            ratio = hv[f] / (h_sum[f] + lv)
                            eig += float(torch.log1p(ratio).sum(dtype=torch.float64))
                            tr += float(ratio.sum(dtype=torch.float64))
                        suffix = _suffix(lv, lam, bname, tag)
                        out.setdefault(f"eig{suffix}", []).append(eig)
                        if not tag:
                            out.setdefault(f"trace{suffix}", []).append(tr)
    return out


def _suffix(lv: float, lam: float, block: str, tag: str) -> str:
    parts = []
    if lv != lam:
        parts.append(f"lam{lv:g}")
    if block != "all":
        parts.append(block)
    if tag:
        parts.append(tag)
    return "" if not parts else "_" + "_".join(parts)


def _shortlist_score(shortlist: Sequence[int], n: int, by: Sequence[float] | None = None
                     ) -> list[float]:
    """A shortlist as a score over n candidates: members above non-members (tied at 0),
    ordered by their position (first = highest) or by ``by`` (higher = higher)."""
    out = [0.0] * n
    k = len(shortlist)
    if by is None:
        for pos, v in enumerate(shortlist):
            out[v] = float(k - pos)
    else:
        order = sorted(shortlist, key=lambda v: by[v])
        for r, v in enumerate(order):
            out[v] = float(r + 1)
    return out


def _select(method: str, ctx: Mapping[str, Any], h_acc: Mapping[str, Tensor], cfg: SelectConfig,
            lam: float) -> Any:
    return select(method, ctx["gmap"], h_acc, ctx["candidates"], ctx["intrinsics"],
                  config=cfg, acquired=ctx["acquired"], lam=lam)


def method_scores(ctx: Mapping[str, Any], lam: float, seed: int
                  ) -> tuple[dict[str, list[float]], dict[str, int], list[int]]:
    """Every score and pick on one event's inputs: (scores [R] each, picks, the default
    shortlist)."""
    gmap, cands, acq, intr = ctx["gmap"], ctx["candidates"], ctx["acquired"], ctx["intrinsics"]
    bg = ctx["background"]
    n = int(cands.shape[0])
    scores = _information_scores(gmap, cands, acq, intr, bg, lam)
    h_acc = {k: torch.full_like(v, lam) for k, v in gmap.items()}
    with torch.no_grad():
        for pose in acq:
            hv = fisher_diag(gmap, Camera(c2w=pose, intrinsics=intr), background=bg)
            for k in h_acc:
                h_acc[k] += hv[k]
    base = SelectConfig(seed=int(seed), fisher_background=tuple(float(c) for c in bg))  # type: ignore[arg-type]
    picks: dict[str, int] = {}
    phi = scores["eig"]
    picks["full_eig"] = max(range(n), key=lambda i: (phi[i], -i))
    picks["random"] = _select("random", ctx, h_acc, base, lam).index
    picks["spread"] = _select("spread", ctx, h_acc, base, lam).index
    fr = _select("fisherrf", ctx, h_acc, base, lam)
    scores["fisherrf"] = [fr.scores[i] for i in range(n)]
    picks["fisherrf"] = fr.index
    cv = _select("cover", ctx, h_acc, base, lam)
    scores["cover"] = [-cv.scores[i] for i in range(n)]
    picks["cover"] = cv.index
    default_shortlist: list[int] = []
    for key in SHORTLISTS:
        v: Variant = parse_variant(key)
        sel = _select("agile", ctx, h_acc, v.config(base), lam)
        name = key.replace("@", "_")
        pool_psi = sel.details.get("pool_proxy_psi") or {}
        if key in ("agile", "agile@cover_zbuffer"):
            scores["anchor_psi" + name[5:]] = [float(pool_psi.get(i, float("nan")))
                                               for i in range(n)]
        scores["shortlist" + name[5:]] = _shortlist_score(sel.shortlist, n)
        if key in ("agile", "agile@paper"):
            plus = max(sel.shortlist, key=lambda i: (phi[i], -sel.shortlist.index(i)))
            picks[key] = sel.index
            picks[key.replace("agile", "agile_plus")] = plus
            scores[name.replace("agile", "agile_plus")] = _shortlist_score(sel.shortlist, n, phi)
        if key == "agile":
            default_shortlist = list(sel.shortlist)
    return scores, picks, default_shortlist


# ----------------------------------------------------------------------------- realised gains
def realised_gains(ctx: Mapping[str, Any], scene: BenchScene, profile: Profile,
                   sample: Sequence[int], horizon: int) -> tuple[float, list[float]]:
    """Test PSNR of a branch trained ``horizon`` steps without a new view, and each sampled
    candidate's gain over it (candidates are indices into ``ctx["candidates"]``)."""
    mapper = ctx["mapper"]
    dev = ctx["gmap"].device
    base = mapper.clone()
    base.step(horizon)
    psnr0 = float(evaluate(base.gmap, scene, device=dev, with_lpips=False, full=False)["psnr"])
    gains = []
    remaining = ctx["remaining"]
    for c in sample:
        branch = mapper.clone()
        add_pool_view(branch, scene, int(remaining[c]), profile, device=dev)
        branch.step(horizon)
        q = float(evaluate(branch.gmap, scene, device=dev, with_lpips=False, full=False)["psnr"])
        gains.append(q - psnr0)
    return psnr0, gains


def value_event(ctx: Mapping[str, Any], scene: BenchScene, profile: Profile, *, seed: int,
                candidates: int, horizon: int) -> dict[str, Any]:
    """One event's record (see the module docstring)."""
    t0 = time.perf_counter()
    n = int(ctx["candidates"].shape[0])
    scores, picks, shortlist = method_scores(ctx, profile.lam, seed)
    t_scores = time.perf_counter() - t0
    chosen = list(dict.fromkeys(list(picks.values()) + list(shortlist)))
    if n <= candidates:
        sample = list(range(n))
    else:
        g = torch.Generator().manual_seed(1_000_003 * seed + 7919 * int(ctx["event"]) + 11)
        rest = [i for i in torch.randperm(n, generator=g).tolist() if i not in set(chosen)]
        sample = sorted(chosen + rest[: max(candidates - len(chosen), 0)])
    psnr0, gains = realised_gains(ctx, scene, profile, sample, horizon)
    gain_of = dict(zip(sample, gains))
    rho = {name: rank_correlation([s[i] for i in sample], gains) for name, s in scores.items()
           if all(math.isfinite(s[i]) for i in sample)}
    pick_out = {m: {"candidate": int(v), "pool_index": int(ctx["remaining"][v]),
                    "gain": gain_of[v], "percentile": gain_percentile(gains, gain_of[v])}
                for m, v in picks.items()}
    return {
        "event": int(ctx["event"]),
        "step": int(ctx["step"]),
        "views": int(ctx["acquired"].shape[0]),
        "remaining": n,
        "horizon": horizon,
        "baseline_psnr": psnr0,
        "sample": [int(ctx["remaining"][i]) for i in sample],
        "gains": gains,
        "scores": {k: [v[i] for i in sample] for k, v in scores.items()},
        "spearman": rho,
        "picks": pick_out,
        "seconds": {"scores": t_scores, "total": time.perf_counter() - t0},
    }


# ----------------------------------------------------------------------------- summary
def _mean(values: Sequence[float]) -> float:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return statistics.fmean(v) if v else float("nan")


def summarise(scenes: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, Any]:
    """Per scene (over events) and overall (over scenes) means of the correlations and of the
    picks' percentiles and gains."""
    per: dict[str, Any] = {}
    for name, events in scenes.items():
        keys = sorted({k for e in events for k in e["spearman"]})
        per[name] = {
            "spearman": {k: _mean([e["spearman"].get(k, float("nan")) for e in events])
                         for k in keys},
            "pick_percentile": {m: _mean([e["picks"][m]["percentile"] for e in events
                                          if m in e["picks"]]) for m in PICKS},
            "pick_gain": {m: _mean([e["picks"][m]["gain"] for e in events if m in e["picks"]])
                          for m in PICKS},
            "events": len(events),
        }
    keys = sorted({k for p in per.values() for k in p["spearman"]})
    overall = {
        "spearman": {k: _mean([p["spearman"].get(k, float("nan")) for p in per.values()])
                     for k in keys},
        "pick_percentile": {m: _mean([p["pick_percentile"][m] for p in per.values()])
                            for m in PICKS},
        "pick_gain": {m: _mean([p["pick_gain"][m] for p in per.values()]) for m in PICKS},
        "scenes": len(per),
    }
    return {"per_scene": per, "overall": overall}


def table(summary: Mapping[str, Any], scene_types: Mapping[str, str]) -> str:
    """Markdown: the correlation of each score per scene and overall, then the picks."""
    per = summary["per_scene"]
    names = list(per)
    keys = list(summary["overall"]["spearman"])
    head = "| score | " + " | ".join(f"{n} ({scene_types.get(n, '?')})" for n in names) + \
        " | mean |"
    lines = ["Spearman of each score with the realised gain (mean over events):", "", head,
             "|---|" + "---|" * (len(names) + 1)]
    for k in keys:
        cells = [f"{per[n]['spearman'].get(k, float('nan')):+.2f}" for n in names]
        lines.append(f"| {k} | " + " | ".join(cells)
                     + f" | {summary['overall']['spearman'][k]:+.2f} |")
    lines += ["", "Where each method's pick falls in the realised-gain ranking of the sample "
              "(percentile, 100 = best; mean over events), and its mean gain (dB):", "",
              "| method | " + " | ".join(names) + " | mean | mean gain |",
              "|---|" + "---|" * (len(names) + 2)]
    for m in PICKS:
        cells = [f"{per[n]['pick_percentile'][m]:.0f}" for n in names]
        lines.append(f"| {m} | " + " | ".join(cells)
                     + f" | {summary['overall']['pick_percentile'][m]:.1f} | "
                     f"{summary['overall']['pick_gain'][m]:+.3f} |")
    return "\n".join(lines) + "\n"


def plot_scene(name: str, events: Sequence[Mapping[str, Any]], path: Path) -> None:
    """Per scene: the correlation of each score with the realised gain (bars: mean over
    events, dots: events), and gain against the exact EIG's rank at the last event."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = sorted({k for e in events for k in e["spearman"]})
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 5), gridspec_kw={"width_ratios": [3, 1]})
    means = [_mean([e["spearman"].get(k, float("nan")) for e in events]) for k in keys]
    ax.bar(range(len(keys)), means, color="#9ecae1")
    for e in events:
        ax.plot(range(len(keys)), [e["spearman"].get(k, float("nan")) for k in keys], ".",
                color="#3182bd", alpha=0.7)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(range(len(keys)), keys, rotation=70, ha="right", fontsize=7)
    ax.set_ylabel("Spearman with realised gain")
    ax.set_title(f"{name}: what predicts a view's worth")
    last = events[-1]
    eig = last["scores"]["eig"]
    ax2.scatter(average_ranks(torch.tensor(eig)).tolist(), last["gains"], s=12)
    for m, mk in (("agile_plus", "*"), ("cover", "s"), ("fisherrf", "^")):
        p = last["picks"][m]
        i = last["sample"].index(p["pool_index"])
        ax2.scatter([float(average_ranks(torch.tensor(eig))[i])], [p["gain"]], marker=mk,
                    s=60, label=m)
    ax2.set_xlabel("rank of exact EIG in the sample")
    ax2.set_ylabel(f"realised gain (dB, {last['horizon']} steps)")
    ax2.set_title(f"event {last['event']}")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- command
def run(args: argparse.Namespace) -> int:
    profile = protocol_profile(args)
    try:
        driver = parse_variant(args.driver)
        wanted = {int(e) for e in str(args.events).split(",") if e.strip()}
    except ValueError as exc:
        raise SystemExit(f"--driver / --events: {exc}") from None
    if args.candidates < 3:
        raise SystemExit("--candidates must be >= 3")
    horizon = int(args.horizon or profile.interval)
    if horizon < 1:
        raise SystemExit("--horizon must be >= 1")
    out: dict[str, Any] = {"profile": profile.name, "seed": args.seed, "driver": args.driver,
                           "horizon": horizon, "candidates": args.candidates, "scenes": {},
                           "types": {}}
    for path in args.scene:
        scene = load_bench_scene(path, profile.scene)
        out["types"][scene.name] = scene.info.get("type", "object")
        events: list[dict[str, Any]] = []

        def on_event(ctx: dict[str, Any], events: list[dict[str, Any]] = events,
                     scene: BenchScene = scene) -> None:
            if ctx["event"] not in wanted:
                return
            rec = value_event(ctx, scene, profile, seed=args.seed, candidates=args.candidates,
                              horizon=horizon)
            events.append(rec)
            log.info("%s event %d: %d candidates, gains %.3f..%.3f dB, rho eig %+.2f "
                     "agile_plus %+.2f cover %+.2f (%.0f s)", scene.name, rec["event"],
                     len(rec["sample"]), min(rec["gains"]), max(rec["gains"]),
                     rec["spearman"].get("eig", float("nan")),
                     rec["spearman"].get("agile_plus", float("nan")),
                     rec["spearman"].get("cover", float("nan")), rec["seconds"]["total"])

        run_progressive(scene, driver, args.seed, profile, on_event=on_event)
        out["scenes"][scene.name] = events
        if args.plots and events:
            Path(args.plots).mkdir(parents=True, exist_ok=True)
            plot_scene(scene.name, events, Path(args.plots) / f"value_{scene.name}.png")
    measured = {k: v for k, v in out["scenes"].items() if v}
    out["summary"] = summarise(measured)
    sys.stdout.write(table(out["summary"], out["types"]))
    if args.json_out:
        Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json_out).write_text(json.dumps(out, indent=1))
    return 0


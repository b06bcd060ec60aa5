"""``results.json`` and ``table.md`` of ``agilegs bench run``.

``results.json`` holds, besides the settings and the environment:

- ``scenes[<scene>]``: the scene's facts, ``runs[<variant>][<seed>]`` (each run's full
  record: ``psnr``, ``ssim``, ``lpips`` (None without local LPIPS weights), ``events`` with
  the per-event ``latency_ms`` breakdown, ``sequence`` / ``selected`` (pool indices in
  acquisition order), ``curve``, ``path_length``, ``mean_index_jump``, ...), and
  ``summary[<variant>]`` (mean and std over seeds);
- ``summary[<variant>]``: the averages over scenes (the paper's "Avg." columns);
- ``paired_psnr[<a>][<b>]``: for the main methods, the PSNR of a minus that of b over the
  (scene, seed) runs both have (same seed: same initial views, training seed and test views,
  so the differences are paired): ``mean``, ``se`` (the standard error of that mean; None
  with one pair), ``wins`` (pairs where a is higher) and ``n``; the same per scene
  (``paired_psnr_by_scene[<scene>]``) and per scene type (``paired_psnr_by_type[<type>]``:
  ``object``, ``capture``, ``posed``);
- latencies per event: ``selection_ms_mean`` (the selection alone: the ``select`` call less
  the information a method rebuilds inside it) and ``event_ms_mean`` (an event of the
  method's own algorithm: FisherRF rebuilds H_train from every training view inside its
  call; the Hhat methods add one committed view's Fisher, ``upkeep_ms``, estimated as the
  event's Hhat recompute divided by its views), with ``fisherrf_over_method`` /
  ``full_eig_over_method`` ratios of both;
- ``invocation``: which (scene, variant, seed) runs this call executed and which it skipped.

Statistics: ``*_mean`` is the mean over seeds, ``*_std`` their sample standard deviation
(0 with one seed). Latencies are means over every selection event of every seed; the
averages over scenes weight scenes equally.

``table.md`` lays the means ± std out as the paper's main results table (one PSNR / SSIM /
LPIPS column group per scene, then the average PSNR and the average selection time per
event), followed by a latency table (with FisherRF's latency over each method's), the
acquisition trajectories (path length, mean frame-index jump), the paired PSNR differences
between the main methods and, when they were run, the shortlist-strategy and shortlist-budget
ablations laid out as the paper's two ablation tables.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from agilegs.lab.bench.profiles import RESULTS_FORMAT
from agilegs.lab.bench.redundancy import redundancy_table, summarise_redundancy
from agilegs.lab.bench.scene_model import BenchScene
from agilegs.lab.bench.stages import anchor_split_table
from agilegs.lab.bench.variants import SHORTLIST_DISPLAY, display_name

__all__ = ["build_results", "scene_summary", "render_table", "mean_std", "paired_differences"]

MAIN_ORDER = ("random", "spread", "fisherrf", "cover", "full_eig", "agile", "agile_plus",
              "agile@paper", "agile_plus@paper")
REFERENCE = "agile_plus"
"""The method whose paired differences are tabulated per scene and per scene type."""


def _selection_ms(e: Mapping[str, Any]) -> float:
    """An event's selection alone: the select call less the information a method rebuilds
    inside it (FisherRF's H_train)."""
    lat = e["latency_ms"]
    return float(lat["total"]) - float(lat.get("information", 0.0))


def _event_ms(e: Mapping[str, Any]) -> float:
    """An event of the method's own algorithm: the select call (FisherRF's rebuild of H_train
    included) plus the upkeep of an incremental Hhat (one committed view's Fisher)."""
    return float(e["latency_ms"]["total"]) + float(e.get("upkeep_ms", 0.0))


def mean_std(values: Iterable[float | None]) -> tuple[float | None, float | None]:
    """(mean, sample std) of the non-None values; (None, None) when there are none."""
    v = [float(x) for x in values if x is not None and not math.isnan(float(x))]
    if not v:
        return None, None
    return statistics.fmean(v), (statistics.stdev(v) if len(v) > 1 else 0.0)


def scene_summary(scene: BenchScene) -> dict[str, Any]:
    """The facts of a scene kept in ``results.json`` (pool poses for the trajectory plots)."""
    return {
        "kind": scene.kind,
        "type": scene.info.get("type", "object"),
        "source": scene.source,
        "pool": scene.pool_size,
        "test": int(scene.test_poses.shape[0]),
        "resolution": [scene.intrinsics.width, scene.intrinsics.height],
        "background": list(scene.background),
        "center": [float(x) for x in scene.center],
        "radius": scene.radius,
        "info": scene.info,
    }


def _summarise_runs(runs: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    recs = list(runs.values())
    out: dict[str, Any] = {"seeds": sorted(int(s) for s in runs)}
    for key in ("psnr", "ssim", "lpips", "path_length", "mean_index_jump", "wall_s"):
        m, s = mean_std(r.get(key) for r in recs)
        out[f"{key}_mean"], out[f"{key}_std"] = m, s
    evs = [e for r in recs for e in r.get("events", [])]
    lat = [e["latency_ms"]["total"] for e in evs]
    info = [e["information_ms"] for e in evs]
    out["latency_ms_mean"] = statistics.fmean(lat) if lat else None
    out["selection_ms_mean"] = statistics.fmean(map(_selection_ms, evs)) if evs else None
    out["event_ms_mean"] = statistics.fmean(map(_event_ms, evs)) if evs else None
    cpu = [e["select_cpu_ms"] for r in recs for e in r.get("events", []) if "select_cpu_ms" in e]
    out["cpu_ms_mean"] = statistics.fmean(cpu) if cpu else None
    out["latency_ms_median"] = statistics.median(lat) if lat else None
    out["latency_ms_seed_std"] = mean_std(r["latency_ms"]["mean"] for r in recs)[1]
    out["information_ms_mean"] = statistics.fmean(info) if info else None
    out["events"] = len(lat)
    stages: dict[str, list[float]] = {}
    for r in recs:
        for e in r.get("events", []):
            for k, v in e["latency_ms"].items():
                stages.setdefault(k, []).append(float(v))
    out["stages_ms_mean"] = {k: statistics.fmean(v) for k, v in stages.items()}
    curve: dict[int, list[float]] = {}
    for r in recs:
        for c in r.get("curve", []):
            curve.setdefault(int(c["views"]), []).append(float(c["psnr"]))
    out["curve"] = [
        {"views": n, "psnr_mean": mean_std(v)[0], "psnr_std": mean_std(v)[1], "runs": len(v)}
        for n, v in sorted(curve.items())
    ]
    out["redundancy"] = summarise_redundancy(recs)
    return out


def paired_differences(
    runs: Mapping[str, Mapping[str, Mapping[str, Mapping[str, Any]]]],
    keys: Sequence[str],
    metric: str = "psnr",
) -> dict[str, dict[str, dict[str, Any]]]:
    """Paired differences of ``metric`` between every two of ``keys``.

    ``runs[scene][variant][seed]`` are run records. For a != b: ``mean`` of
    ``run_a[metric] - run_b[metric]`` over the (scene, seed) pairs where both ran (with a
    value), ``se`` its standard error (sample std / sqrt(n); None when n < 2), ``wins`` the
    pairs where a is strictly higher, ``n`` the pairs; ``mean`` None when n = 0.
    """
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for a in keys:
        for b in keys:
            if a == b:
                continue
            diffs: list[float] = []
            for by_variant in runs.values():
                ra, rb = by_variant.get(a, {}), by_variant.get(b, {})
                for seed in sorted(set(ra) & set(rb)):
                    va, vb = ra[seed].get(metric), rb[seed].get(metric)
                    if va is None or vb is None or math.isnan(va) or math.isnan(vb):
                        continue
                    diffs.append(float(va) - float(vb))
            n = len(diffs)
            out.setdefault(a, {})[b] = {
                "mean": statistics.fmean(diffs) if n else None,
                "se": statistics.stdev(diffs) / math.sqrt(n) if n > 1 else None,
                "wins": sum(d > 0 for d in diffs),
                "n": n,
            }
    return out


def build_results(
    *,
    records: Mapping[tuple[str, str, int], Mapping[str, Any]],
    scenes: Mapping[str, Mapping[str, Any]],
    variants: Sequence[Mapping[str, Any]],
    seeds: Sequence[int],
    profile: Mapping[str, Any],
    settings: Mapping[str, Any],
    environment: Mapping[str, Any],
    invocation: Mapping[str, Any],
) -> dict[str, Any]:
    """Gather run records into the ``results.json`` structure (see the module docstring)."""
    out_scenes: dict[str, Any] = {}
    for name, facts in scenes.items():
        runs: dict[str, dict[str, Any]] = {}
        for v in variants:
            for s in seeds:
                rec = records.get((name, v["key"], int(s)))
                if rec is not None:
                    runs.setdefault(v["key"], {})[str(int(s))] = dict(rec)
        summary = {k: _summarise_runs({int(s): r for s, r in rs.items()})
                   for k, rs in runs.items()}
        out_scenes[name] = {**facts, "runs": runs, "summary": summary}
    overall: dict[str, Any] = {}
    for v in variants:
        per = [out_scenes[n]["summary"].get(v["key"]) for n in out_scenes]
        per = [p for p in per if p is not None]
        if not per:
            continue
        evs = [e for n in out_scenes
               for r in out_scenes[n]["runs"].get(v["key"], {}).values() for e in r["events"]]
        lat = [e["latency_ms"]["total"] for e in evs]
        cpu = [e["select_cpu_ms"] for e in evs if "select_cpu_ms" in e]
        overall[v["key"]] = {
            "psnr_mean": mean_std(p["psnr_mean"] for p in per)[0],
            "selection_ms_mean": statistics.fmean(map(_selection_ms, evs)) if evs else None,
            "event_ms_mean": statistics.fmean(map(_event_ms, evs)) if evs else None,
            "ssim_mean": mean_std(p["ssim_mean"] for p in per)[0],
            "lpips_mean": mean_std(p["lpips_mean"] for p in per)[0],
            "latency_ms_mean": statistics.fmean(lat) if lat else None,
            "latency_ms_median": statistics.median(lat) if lat else None,
            "cpu_ms_mean": statistics.fmean(cpu) if cpu else None,
            "path_length_mean": mean_std(p["path_length_mean"] for p in per)[0],
            "mean_index_jump_mean": mean_std(p["mean_index_jump_mean"] for p in per)[0],
            "redundancy": {k: mean_std(p["redundancy"][k] for p in per)[0]
                           for k in per[0]["redundancy"]},
            "scenes": len(per),
        }
    for ref in ("fisherrf", "full_eig"):
        r = overall.get(ref, {})
        for o in overall.values():
            for field, suffix in (("selection_ms_mean", ""), ("event_ms_mean", "_event"),
                                  ("cpu_ms_mean", "_cpu")):
                num, den = r.get(field), o.get(field)
                o[f"{ref}_over_method{suffix}"] = (num / den) if num and den else None
    main_keys = [v["key"] for v in variants if v.get("group") == "main" and v["key"] in overall]
    all_runs = {n: out_scenes[n]["runs"] for n in out_scenes}
    paired = paired_differences(all_runs, main_keys)
    by_scene = {n: paired_differences({n: all_runs[n]}, main_keys) for n in out_scenes}
    types = sorted({str(out_scenes[n].get("type", "object")) for n in out_scenes})
    by_type = {
        t: paired_differences({n: all_runs[n] for n in out_scenes
                               if str(out_scenes[n].get("type", "object")) == t}, main_keys)
        for t in types
    }
    return {
        "format": RESULTS_FORMAT,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "profile": dict(profile),
        "settings": dict(settings),
        "environment": dict(environment),
        "seeds": [int(s) for s in seeds],
        "variants": [dict(v) for v in variants],
        "scenes": out_scenes,
        "summary": overall,
        "paired_psnr": paired,
        "paired_psnr_by_scene": by_scene,
        "paired_psnr_by_type": by_type,
        "invocation": dict(invocation),
    }


# ----------------------------------------------------------------------------- markdown
def _display(key: str) -> str:
    return display_name(key)


def _fmt(m: float | None, s: float | None, digits: int) -> str:
    if m is None:
        return "–"
    if s is None:
        return f"{m:.{digits}f}"
    return f"{m:.{digits}f} ± {s:.{digits}f}"


def _rank_marks(values: Mapping[str, float | None], higher: bool) -> dict[str, str]:
    """'best' / 'second' marks (bold / italic) among the non-None values."""
    vals = [(k, v) for k, v in values.items() if v is not None]
    if len(vals) < 2:
        return {}
    order = sorted(vals, key=lambda kv: kv[1], reverse=higher)
    marks = {order[0][0]: "best"}
    if len(order) > 2:
        marks[order[1][0]] = "second"
    return marks


def _mark(text: str, mark: str | None) -> str:
    if mark == "best":
        return f"**{text}**"
    if mark == "second":
        return f"_{text}_"
    return text


def _variants_in(results: Mapping[str, Any], group: str) -> list[str]:
    return [v["key"] for v in results["variants"] if v["group"] == group
            and v["key"] in results["summary"]]


def _main_rows(results: Mapping[str, Any]) -> list[str]:
    keys = [k for k in MAIN_ORDER if k in results["summary"]]
    keys += [k for k in _variants_in(results, "main") if k not in keys]
    return keys


def render_table(results: Mapping[str, Any]) -> str:
    """``table.md``: the paper's main results table and the companion tables."""
    scenes = list(results["scenes"])
    prof = results["profile"]
    seeds = results["seeds"]
    emb = results["settings"].get("embodied_k")
    lines = [
        f"# agilegs bench run: `{prof['name']}` profile",
        "",
        f"Scenes: {', '.join(scenes)}; seeds: {', '.join(map(str, seeds))}; "
        f"{prof['initial_views']} initial views, one selection every {prof['interval']} steps"
        f" up to {prof['view_budget'] or 'the step budget'} views, {prof['total_steps']} steps; "
        f"shortlist N = {prof['shortlist_size']}"
        + (f"; **embodied**: K = {emb} nearest candidates" if emb else "") + ".",
        "Values are mean ± std over seeds; **bold** best, _italic_ second best. Selection time "
        "is the mean latency of the selection alone per acquisition event (see the latency "
        "table for the per-event cost with each method's information upkeep). Scenes by type: "
        + _scene_types(results, scenes) + ". LPIPS is – when its weights are not available "
        "locally.",
        "",
    ]
    keys = _main_rows(results)
    if keys:
        lines += _main_table(results, scenes, keys)
        lines += _latency_table(results, keys)
        lines += anchor_split_table(results, keys, _display)
        lines += _trajectory_table(results, keys, emb)
        lines += redundancy_table(
            [(_display(k), results["summary"][k].get("redundancy") or {}) for k in keys])
        lines += _paired_table(results, keys)
        lines += _paired_by_table(results, keys)
    # the ablations' reference rows (the paper's settings) are the main agile / agile_plus runs
    sl = _variants_in(results, "shortlist")
    if sl:
        ref = results["settings"].get("shortlist_method", "agile")
        lines += _shortlist_table(results, sl + [k for k in (ref,)
                                                 if k in results["summary"]], ref)
    bud = _variants_in(results, "budget")
    if bud:
        lines += _budget_table(results, bud + [k for k in ("agile_plus",)
                                               if k in results["summary"]])
    return "\n".join(lines) + "\n"


def _scene_types(results: Mapping[str, Any], scenes: list[str]) -> str:
    types: dict[str, list[str]] = {}
    for n in scenes:
        types.setdefault(str(results["scenes"][n].get("type", "object")), []).append(n)
    return "; ".join(f"{t}: {', '.join(ns)}" for t, ns in sorted(types.items()))


def _main_table(results: Mapping[str, Any], scenes: list[str], keys: list[str]) -> list[str]:
    head = "| Method |"
    sep = "|---|"
    for s in scenes:
        head += f" {s} PSNR↑ | {s} SSIM↑ | {s} LPIPS↓ |"
        sep += "---|---|---|"
    head += " Avg. PSNR↑ | Avg. selection time (s)↓ |"
    sep += "---|---|"
    marks: dict[tuple[str, str], dict[str, str]] = {}
    for s in scenes:
        summ = results["scenes"][s]["summary"]
        for metric, higher in (("psnr", True), ("ssim", True), ("lpips", False)):
            marks[(s, metric)] = _rank_marks(
                {k: summ.get(k, {}).get(f"{metric}_mean") for k in keys}, higher)
    avg = results["summary"]
    marks[("avg", "psnr")] = _rank_marks({k: avg[k]["psnr_mean"] for k in keys}, True)
    marks[("avg", "time")] = _rank_marks({k: avg[k]["selection_ms_mean"] for k in keys}, False)
    rows = ["## Main results", "", head, sep]
    for k in keys:
        row = f"| {_display(k)} |"
        for s in scenes:
            summ = results["scenes"][s]["summary"].get(k)
            for metric, digits in (("psnr", 3), ("ssim", 4), ("lpips", 4)):
                if summ is None:
                    row += " – |"
                    continue
                txt = _fmt(summ[f"{metric}_mean"], summ[f"{metric}_std"], digits)
                row += f" {_mark(txt, marks[(s, metric)].get(k))} |"
        a = avg[k]
        row += f" {_mark(_fmt(a['psnr_mean'], None, 3), marks[('avg', 'psnr')].get(k))} |"
        t = a["selection_ms_mean"]
        row += f" {_mark('–' if t is None else f'{t / 1e3:.3f}', marks[('avg', 'time')].get(k))} |"
        rows.append(row)
    return rows + [""]


def _latency_table(results: Mapping[str, Any], keys: list[str]) -> list[str]:
    rows = [
        "## Selection latency per event",
        "",
        "Wall-clock milliseconds per event (means). *Selection*: the `select` call less the "
        "information a method rebuilds inside it; *per event*: an event of the method's own "
        "algorithm, i.e. FisherRF's call with its rebuild of H_train from every training view "
        "(*H_train*), and for the Ĥ methods the selection plus one committed view's Fisher "
        "added to Ĥ (estimated from the protocol's Ĥ recompute, which is reported apart: the "
        "protocol recomputes Ĥ on the current map for every Ĥ method alike). Stages are the "
        "`select` breakdown; CPU is the process CPU time of the same calls (on a shared "
        "machine the wall clock carries other processes' load).",
        "",
        "| Method | selection (ms) | per event (ms) | H_train | anchor | scoring | leverage | "
        "rerank | CPU (ms) | Ĥ recompute (ms, apart) | FisherRF / method (selection) | "
        "FisherRF / method (per event) | full EIG / method (selection) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k in keys:
        a = results["summary"][k]
        stages: dict[str, list[float]] = {}
        info: list[float] = []
        for s in results["scenes"].values():
            summ = s["summary"].get(k)
            if summ is None:
                continue
            for st, v in summ["stages_ms_mean"].items():
                stages.setdefault(st, []).append(v)
            if summ["information_ms_mean"] is not None:
                info.append(summ["information_ms_mean"])

        def st(name: str, stages: dict[str, list[float]] = stages) -> str:
            v = stages.get(name)
            return f"{statistics.fmean(v):.1f}" if v else "–"

        rows.append(
            f"| {_display(k)} | {_num(a.get('selection_ms_mean'), 1)} | "
            f"{_num(a.get('event_ms_mean'), 1)} | {st('information')} | {st('anchor')} | "
            f"{st('scoring')} | {st('leverage')} | {st('rerank')} | "
            f"{_num(a.get('cpu_ms_mean'), 1)} | "
            f"{_num(statistics.fmean(info) if info else None, 1)} | "
            f"{_times(a.get('fisherrf_over_method'))} | "
            f"{_times(a.get('fisherrf_over_method_event'))} | "
            f"{_times(a.get('full_eig_over_method'))} |"
        )
    return rows + [""]


def _times(v: float | None) -> str:
    return "–" if v is None else f"{v:.1f}×"


def _paired_cell(d: Mapping[str, Any] | None) -> str:
    if d is None or d["mean"] is None:
        return "–"
    se = "" if d["se"] is None else f" ± {d['se']:.2f}"
    return f"{d['mean']:+.2f}{se} ({d['wins']}/{d['n']})"


def _paired_by_table(results: Mapping[str, Any], keys: list[str]) -> list[str]:
    ref = REFERENCE
    by_scene = results.get("paired_psnr_by_scene") or {}
    by_type = results.get("paired_psnr_by_type") or {}
    others = [k for k in keys if k != ref]
    if ref not in keys or not others or not by_scene:
        return []
    name = _display(ref)
    head = f"| | {' | '.join(f'{name} − {_display(k)}' for k in others)} |"
    sep = "|---|" + "---|" * len(others)
    rows = [
        f"## Paired PSNR differences of {name}, per scene type and per scene",
        "",
        f"{name} minus each method, in dB, over the seeds of each scene (mean ± standard error, "
        "and runs where it is higher / runs).",
        "",
        head,
        sep,
    ]
    for t, paired in by_type.items():
        cells = [_paired_cell(paired.get(ref, {}).get(k)) for k in others]
        rows.append(f"| **{t}** | " + " | ".join(cells) + " |")
    for scene, paired in by_scene.items():
        t = results["scenes"][scene].get("type", "object")
        cells = [_paired_cell(paired.get(ref, {}).get(k)) for k in others]
        rows.append(f"| {scene} ({t}) | " + " | ".join(cells) + " |")
    return rows + [""]


def _paired_table(results: Mapping[str, Any], keys: list[str]) -> list[str]:
    paired = results.get("paired_psnr") or {}
    keys = [k for k in keys if k in paired]
    if len(keys) < 2:
        return []
    rows = [
        "## Paired PSNR differences",
        "",
        "Row minus column, in dB, over the (scene, seed) runs both have (one seed gives every "
        "method the same initial views, training seed and test views, so the differences are "
        "paired): mean ± its standard error, and (runs where the row is higher / runs). A "
        "difference within about two standard errors of 0 is within the seeds' noise.",
        "",
        "| row − column | " + " | ".join(_display(k) for k in keys) + " |",
        "|---|" + "---|" * len(keys),
    ]
    for a in keys:
        cells = []
        for b in keys:
            cells.append(_paired_cell(paired[a].get(b) if a != b else None))
        rows.append(f"| {_display(a)} | " + " | ".join(cells) + " |")
    return rows + [""]


def _num(v: float | None, digits: int) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def _trajectory_table(results: Mapping[str, Any], keys: list[str], emb: int | None) -> list[str]:
    title = "## Acquisition trajectories" + (f" (embodied, K = {emb})" if emb else "")
    rows = [
        title,
        "",
        "Path length: sum of camera-centre distances from the last initial view through every "
        "selected view (scene units); frame-index jump: mean |difference| of consecutive pool "
        "indices (capture order).",
        "",
        "| Method | path length | mean frame-index jump |",
        "|---|---|---|",
    ]
    for k in keys:
        a = results["summary"][k]
        rows.append(f"| {_display(k)} | {_num(a['path_length_mean'], 3)} | "
                    f"{_num(a['mean_index_jump_mean'], 2)} |")
    return rows + [""]


def _ablation_rows(results: Mapping[str, Any], keys: list[str], ref: str | None,
                   label: Any) -> list[str]:
    rows = []
    ref_lat = results["summary"].get(ref, {}).get("latency_ms_mean") if ref else None
    for k in keys:
        a = results["summary"][k]
        lat = a["latency_ms_mean"]
        speed = f"{ref_lat / lat:.2f}×" if ref_lat and lat else "–"
        rows.append(f"| {label(k)} | {_num(a['psnr_mean'], 3)} | {_num(a['ssim_mean'], 4)} | "
                    f"{_num(a['lpips_mean'], 4)} | {_num(lat, 1)} | {speed} |")
    return rows


def _shortlist_table(results: Mapping[str, Any], keys: list[str], ref: str) -> list[str]:
    order = {f"{ref}@knearest": 0, f"{ref}@online": 1, f"{ref}@topnorm": 2, ref: 3}
    keys = sorted(keys, key=lambda k: order.get(k, 9))
    by_key = {v["key"]: v for v in results["variants"]}
    name = _display(ref)

    def label(k: str) -> str:
        s = by_key[k]["shortlist"]
        return f"{name} (ours: ridge leverage)" if s == "leverage" else SHORTLIST_DISPLAY.get(s, k)

    note = []
    if ref == "agile":
        note = ["AGILE-GS takes the shortlist's first view; the first greedy ridge-leverage pick "
                "(S_0 = λ_G I) is the largest-norm row, so top independent norm and ridge "
                "leverage choose the same views by construction.", ""]
    return [
        f"## Ablation: shortlist strategy ({name}), averaged over scenes",
        "",
        *note,
        f"| Strategy | PSNR↑ | SSIM↑ | LPIPS↓ | latency (ms) | Speed-up vs {name} |",
        "|---|---|---|---|---|---|",
        *_ablation_rows(results, keys, ref if ref in results["summary"] else None, label),
        "",
    ]


def _budget_table(results: Mapping[str, Any], keys: list[str]) -> list[str]:
    by_key = {v["key"]: v for v in results["variants"]}
    keys = sorted(keys, key=lambda k: by_key[k]["shortlist_size"])
    ref = "agile_plus" if "agile_plus" in results["summary"] else None
    return [
        "## Ablation: AGILE-GS+ shortlist budget N, averaged over scenes",
        "",
        "| N | PSNR↑ | SSIM↑ | LPIPS↓ | latency (ms) | Speed-up vs the default N |",
        "|---|---|---|---|---|---|",
        *_ablation_rows(results, keys, ref, lambda k: str(by_key[k]["shortlist_size"])),
        "",
    ]

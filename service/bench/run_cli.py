"""``agilegs bench run``: the command line of the progressive protocol
(:mod:`agilegs.service.bench.protocol`), its output folder and its resumable runs.

Writes ``DIR/runs/<scene>/<variant>/seed<k>.json`` per run (a rerun with the same ``DIR``
skips the runs whose file exists with the same settings), ``DIR/results.json``,
``DIR/table.md`` and PNG plots (:mod:`agilegs.service.bench.report`,
:mod:`agilegs.service.bench.plots`).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from torch import Tensor

from agilegs.client.ros2 import BagTopics

from . import plots, report
from .options import add_run_arguments as add_arguments
from .profiles import resolve_profile
from .protocol import estimate_seconds, fingerprint, run_progressive
from .scene_model import BenchScene
from .scenes import load_bench_scene
from .variants import build_variants

__all__ = ["add_arguments", "environment", "run"]

log = logging.getLogger(__name__)


def _int_list(text: str, what: str) -> list[int]:
    try:
        return [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"{what}: expected comma-separated integers, got {text!r}") from None


def _str_list(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def _run_path(out: Path, scene: str, variant: str, seed: int) -> Path:
    return out / "runs" / scene / variant.replace("@", "_at_") / f"seed{seed}.json"


def _load_done(path: Path, fingerprint: str) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("%s unreadable (%s): running it again", path, exc)
        return None
    if rec.get("fingerprint") != fingerprint:
        log.warning("%s was made with other settings: running it again", path)
        return None
    return dict(rec)


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=1, default=_json_default))
    os.replace(tmp, path)


def _json_default(o: Any) -> Any:
    if isinstance(o, Tensor):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def environment() -> dict[str, Any]:
    return {
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def run(args: argparse.Namespace) -> int:
    console = Console(stderr=True)
    profile = resolve_profile(args)
    threads = args.threads if args.threads > 0 else profile.threads
    if threads:
        torch.set_num_threads(threads)
    try:
        variants = build_variants(
            _str_list(args.methods), profile.shortlist_size,
            _str_list(args.shortlist_strategies),
            _int_list(args.budgets, "--budgets"),
            args.shortlist_method,
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    seeds = _int_list(args.seeds, "--seeds")
    if not seeds or not variants:
        raise SystemExit("--seeds and --methods must name at least one seed and method")
    if args.embodied is not None and args.embodied < 1:
        raise SystemExit(f"--embodied must be >= 1, got {args.embodied}")
    device = torch.device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    scenes: dict[str, BenchScene] = {}
    try:
        bag_topics = BagTopics.parse(args.bag_topics) if args.bag_topics else None
    except ValueError as exc:
        raise SystemExit(f"--bag-topics: {exc}") from None
    for path in args.scene:
        try:
            sc = load_bench_scene(path, profile.scene, bag_topics=bag_topics)
        except (FileNotFoundError, ValueError) as exc:
            raise SystemExit(f"--scene {path}: {exc}") from None
        if sc.name in scenes:
            raise SystemExit(f"--scene: two scenes are named {sc.name!r}")
        if sc.pool_size < profile.initial_views + 1:
            raise SystemExit(f"--scene {path}: its pool ({sc.pool_size} views) must exceed the "
                             f"{profile.initial_views} initial views")
        scenes[sc.name] = sc
    estimates = {}
    for name, sc in scenes.items() if not args.report_only else ():
        est = estimate_seconds(sc, variants, seeds, profile, device=device,
                               embodied_k=args.embodied)
        estimates[name] = est
        console.print(f"[bold]{name}[/]: estimated {sum(est.values()) / 60:.1f} min for "
                      f"{len(variants)} methods x {len(seeds)} seeds ("
                      + ", ".join(f"{k} {v / 60:.1f}" for k, v in est.items()) + " min)")
    total_est = sum(sum(e.values()) for e in estimates.values())
    console.print(f"estimated total: {total_est / 60:.1f} min on {torch.get_num_threads()} "
                  f"threads ({profile.name} profile)")
    if args.estimate_only:
        return 0

    jobs = [(name, v, s) for name in scenes for s in seeds for v in variants]
    executed: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []
    missing: list[dict[str, Any]] = []
    records: dict[tuple[str, str, int], dict[str, Any]] = {}
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console, transient=False) as bar:
        overall = bar.add_task("runs", total=len(jobs))
        for name, v, s in jobs:
            sc = scenes[name]
            fp = fingerprint(sc, v, s, profile, args.embodied)
            path = _run_path(out, name, v.key, s)
            done = _load_done(path, fp)
            tag = {"scene": name, "variant": v.key, "seed": s}
            if done is not None:
                log.info("skip %s / %s / seed %d: done (%s)", name, v.key, s, path)
                skipped.append(tag)
                records[(name, v.key, s)] = done
                bar.advance(overall)
                continue
            if args.report_only:
                missing.append(tag)
                bar.advance(overall)
                continue
            task = bar.add_task(f"{name} {v.key} s{s}", total=profile.total_steps)

            def on_progress(done_steps: int, total: int, note: str, task: Any = task,
                            label: str = f"{name} {v.key} s{s}") -> None:
                bar.update(task, completed=done_steps, total=total,
                           description=f"{label} ({note})")

            rec = run_progressive(sc, v, s, profile, embodied_k=args.embodied, device=device,
                                  progress=on_progress)
            _write_json(path, rec)
            records[(name, v.key, s)] = rec
            executed.append(tag)
            bar.remove_task(task)
            bar.advance(overall)
            log.info("%s / %s / seed %d: PSNR %.2f dB, SSIM %.4f, %.1f ms per selection, "
                     "%.0f s", name, v.key, s, rec["psnr"], rec["ssim"],
                     rec["latency_ms"]["mean"] or 0.0, rec["wall_s"])
    results = report.build_results(
        records=records,
        scenes={n: report.scene_summary(sc) for n, sc in scenes.items()},
        variants=[asdict(v) for v in variants],
        seeds=seeds,
        profile=profile.describe(),
        settings={"embodied_k": args.embodied, "device": str(device),
                  "shortlist_method": args.shortlist_method,
                  "threads": torch.get_num_threads(), "estimate_s": estimates,
                  "args": {k: v for k, v in vars(args).items() if not k.startswith("_")}},
        environment=environment(),
        invocation={"executed": executed, "skipped": skipped, "missing": missing,
                    "wall_s": time.perf_counter() - t_start},
    )
    _write_json(out / "results.json", results)
    table = report.render_table(results)
    (out / "table.md").write_text(table)
    if not args.no_plots:
        written = plots.write_plots(results, scenes, out)
        log.info("plots: %s", ", ".join(str(p.name) for p in written))
    sys.stdout.write(table)
    sys.stdout.flush()
    console.print(f"{len(executed)} runs done, {len(skipped)} skipped"
                  + (f", {len(missing)} missing" if missing else "") + f"; wrote {out}")
    return 0

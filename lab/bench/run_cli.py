"""``agilegs bench run``: the command line of the progressive protocol
(:mod:`agilegs.lab.bench.protocol`), its output folder and its resumable runs.

Writes ``DIR/runs/<scene>/<variant>/seed<k>.json`` per run (a rerun with the same ``DIR``
skips the runs whose file exists with the same settings), ``DIR/results.json``,
``DIR/table.md`` and PNG plots (:mod:`agilegs.lab.bench.report`,
:mod:`agilegs.lab.bench.plots`). :func:`run` is :func:`parse` (the checked options and the
scenes: a :class:`RunPlan`), :func:`estimate`, :func:`run_jobs` (a :class:`RunOutcome` of
:class:`Job` s), :func:`summarise` (``results.json``'s content) and :func:`write`.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, field
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
from .estimate import estimate_seconds
from .options import add_run_arguments as add_arguments
from .options import flag_values, int_list, protocol_profile, str_list
from .profiles import Profile
from .protocol import fingerprint, run_progressive
from .scene_model import BenchScene
from .scenes import load_bench_scene
from .variants import Variant, build_variants

__all__ = ["Job", "RunOutcome", "RunPlan", "add_arguments", "environment", "estimate", "parse",
           "run", "run_jobs", "summarise", "write"]

log = logging.getLogger(__name__)


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


@dataclass(frozen=True)
class Job:
    """One run of the protocol: a scene, a method (its variant key) and a seed."""

    scene: str
    variant: str
    seed: int


@dataclass
class RunPlan:
    """What ``agilegs bench run`` was asked for, checked: the profile, the methods, the seeds,
    the loaded scenes and the output folder."""

    profile: Profile
    variants: list[Variant]
    seeds: list[int]
    scenes: dict[str, BenchScene]
    device: torch.device
    out: Path
    embodied_k: int | None
    eig_mass: bool = False

    def jobs(self) -> list[Job]:
        return [Job(name, v.key, s) for name in self.scenes for s in self.seeds
                for v in self.variants]

    def variant(self, key: str) -> Variant:
        return next(v for v in self.variants if v.key == key)


@dataclass
class RunOutcome:
    """The runs' records by job, and which jobs ran, were found done, or are missing."""

    records: dict[Job, dict[str, Any]] = field(default_factory=dict)
    executed: list[Job] = field(default_factory=list)
    skipped: list[Job] = field(default_factory=list)
    missing: list[Job] = field(default_factory=list)


def run(args: argparse.Namespace) -> int:
    console = Console(stderr=True)
    t_start = time.perf_counter()
    plan = parse(args)
    warmup_s = None
    if not args.report_only:  # the kernels' compile, apart from every selection's latency
        from agilegs.service.nbv.warmup import warm_up

        warmup_s = warm_up()["total"]
        console.print(f"kernels compiled (or loaded from numba's cache) in {warmup_s:.1f} s, "
                      "before any timed selection")
    estimates = {} if args.report_only else estimate(plan, console)
    if args.estimate_only:
        return 0
    outcome = run_jobs(plan, console, report_only=args.report_only)
    results = summarise(plan, outcome, estimates, args, wall_s=time.perf_counter() - t_start,
                        warmup_s=warmup_s)
    write(plan, results, plots_too=not args.no_plots)
    console.print(f"{len(outcome.executed)} runs done, {len(outcome.skipped)} skipped"
                  + (f", {len(outcome.missing)} missing" if outcome.missing else "")
                  + f"; wrote {plan.out}")
    return 0


def parse(args: argparse.Namespace) -> RunPlan:
    """The command line, checked, and the scenes loaded; ``SystemExit`` naming the flag of
    a bad value. Creates the output folder."""
    profile = protocol_profile(args)
    with flag_values("--methods"):
        variants = build_variants(
            str_list(args.methods), profile.shortlist_size,
            str_list(args.shortlist_strategies),
            int_list(args.budgets, "--budgets"),
            args.shortlist_method,
        )
    seeds = int_list(args.seeds, "--seeds")
    if not seeds or not variants:
        raise SystemExit("--seeds and --methods must name at least one seed and method")
    if args.embodied is not None and args.embodied < 1:
        raise SystemExit(f"--embodied must be >= 1, got {args.embodied}")
    with flag_values("--bag-topics"):
        bag_topics = BagTopics.parse(args.bag_topics) if args.bag_topics else None
    plan = RunPlan(profile, variants, seeds, {}, torch.device(args.device), Path(args.out),
                   args.embodied, bool(getattr(args, "eig_mass", False)))
    plan.out.mkdir(parents=True, exist_ok=True)
    for path in args.scene:
        try:
            sc = load_bench_scene(path, profile.scene, bag_topics=bag_topics)
        except (FileNotFoundError, ValueError) as exc:
            raise SystemExit(f"--scene {path}: {exc}") from None
        if sc.name in plan.scenes:
            raise SystemExit(f"--scene: two scenes are named {sc.name!r}")
        if sc.pool_size < profile.initial_views + 1:
            raise SystemExit(f"--scene {path}: its pool ({sc.pool_size} views) must exceed the "
                             f"{profile.initial_views} initial views")
        plan.scenes[sc.name] = sc
    return plan


def estimate(plan: RunPlan, console: Console) -> dict[str, dict[str, float]]:
    """The estimated seconds per scene and variant (all seeds), printed."""
    estimates = {}
    for name, sc in plan.scenes.items():
        est = estimate_seconds(sc, plan.variants, plan.seeds, plan.profile, device=plan.device,
                               embodied_k=plan.embodied_k)
        estimates[name] = est
        console.print(f"[bold]{name}[/]: estimated {sum(est.values()) / 60:.1f} min for "
                      f"{len(plan.variants)} methods x {len(plan.seeds)} seeds ("
                      + ", ".join(f"{k} {v / 60:.1f}" for k, v in est.items()) + " min)")
    total_est = sum(sum(e.values()) for e in estimates.values())
    console.print(f"estimated total: {total_est / 60:.1f} min on {torch.get_num_threads()} "
                  f"threads ({plan.profile.name} profile)")
    return estimates


def run_jobs(plan: RunPlan, console: Console, *, report_only: bool) -> RunOutcome:
    """Every job whose record is not in the output folder with the same settings, each
    written there as it finishes (``report_only``: none, those missing listed)."""
    outcome = RunOutcome()
    jobs = plan.jobs()
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console, transient=False) as bar:
        overall = bar.add_task("runs", total=len(jobs))
        for job in jobs:
            sc, v = plan.scenes[job.scene], plan.variant(job.variant)
            path = _run_path(plan.out, job.scene, job.variant, job.seed)
            done = _load_done(path, fingerprint(sc, v, job.seed, plan.profile, plan.embodied_k,
                                                plan.eig_mass))
            if done is not None:
                log.info("skip %s / %s / seed %d: done (%s)", job.scene, job.variant, job.seed,
                         path)
                outcome.skipped.append(job)
                outcome.records[job] = done
            elif report_only:
                outcome.missing.append(job)
            else:
                label = f"{job.scene} {job.variant} s{job.seed}"
                task = bar.add_task(label, total=plan.profile.total_steps)

                def on_progress(done_steps: int, total: int, note: str, task: Any = task,
                                label: str = label) -> None:
                    bar.update(task, completed=done_steps, total=total,
                               description=f"{label} ({note})")

                rec = run_progressive(sc, v, job.seed, plan.profile, embodied_k=plan.embodied_k,
                                      device=plan.device, progress=on_progress,
                                      eig_mass=plan.eig_mass)
                _write_json(path, rec)
                outcome.records[job] = rec
                outcome.executed.append(job)
                bar.remove_task(task)
                log.info("%s / %s / seed %d: PSNR %.2f dB, SSIM %.4f, %.1f ms per selection, "
                         "%.0f s", job.scene, job.variant, job.seed, rec["psnr"], rec["ssim"],
                         rec["latency_ms"]["mean"] or 0.0, rec["wall_s"])
            bar.advance(overall)
    return outcome


def summarise(plan: RunPlan, outcome: RunOutcome, estimates: dict[str, dict[str, float]],
              args: argparse.Namespace, *, wall_s: float, warmup_s: float | None = None
              ) -> dict[str, Any]:
    """``results.json``'s content: the records, the scenes, the settings, the machine (and
    the seconds the kernels' warm-up took, apart from the selections')."""
    return report.build_results(
        records={(j.scene, j.variant, j.seed): r for j, r in outcome.records.items()},
        scenes={n: report.scene_summary(sc) for n, sc in plan.scenes.items()},
        variants=[asdict(v) for v in plan.variants],
        seeds=plan.seeds,
        profile=plan.profile.describe(),
        settings={"embodied_k": plan.embodied_k, "device": str(plan.device),
                  "eig_mass": plan.eig_mass,
                  "shortlist_method": args.shortlist_method,
                  "threads": torch.get_num_threads(), "estimate_s": estimates,
                  "kernel_warmup_s": warmup_s,
                  "args": {k: v for k, v in vars(args).items() if not k.startswith("_")}},
        environment=environment(),
        invocation={"executed": [asdict(j) for j in outcome.executed],
                    "skipped": [asdict(j) for j in outcome.skipped],
                    "missing": [asdict(j) for j in outcome.missing],
                    "wall_s": wall_s},
    )


def write(plan: RunPlan, results: dict[str, Any], *, plots_too: bool) -> None:
    """``results.json``, ``table.md`` (also on stdout) and the plots in the output folder."""
    _write_json(plan.out / "results.json", results)
    table = report.render_table(results)
    (plan.out / "table.md").write_text(table)
    if plots_too:
        written = plots.write_plots(results, plan.scenes, plan.out)
        log.info("plots: %s", ", ".join(str(p.name) for p in written))
    sys.stdout.write(table)
    sys.stdout.flush()

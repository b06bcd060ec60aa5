"""The tables of notebook/2026-11-28-objective.md from the campaigns' `bench run` folders.

Ran at commit e6c1258 over folders made at 66af9b1 (cpu_long: random, spread, agile,
agile_plus, the full anchor), a1b4ff1 (cpu: the objective as first built) and d606b7b (cpu, the
captures, cpu_long's target runs), where `agile` / `agile_plus` were the EIG and `@target` the
target objective. Usage:

    python tables.py paired FOLDERS SCENES A:B[,C:D...]   # paired PSNR differences
    python tables.py cost FOLDER VARIANTS                 # selection wall / CPU ms per event
    python tables.py scenes FOLDERS SCENES VARIANTS       # final PSNR per scene

FOLDERS, SCENES and VARIANTS are comma-separated; a later folder's run of a (scene, variant,
seed) replaces an earlier one's.
"""

from __future__ import annotations

import glob
import json
import math
import sys

Key = tuple[str, str, int]


def load(folders: list[str], scenes: set[str]) -> dict[Key, dict]:
    """Every run of ``scenes`` in ``folders``: (scene, variant, seed) -> its JSON."""
    out: dict[Key, dict] = {}
    for folder in folders:
        for path in sorted(glob.glob(f"{folder}/runs/*/*/seed*.json")):
            with open(path) as f:
                run = json.load(f)
            if run["scene"] in scenes:
                out[(run["scene"], run["variant"], run["seed"])] = run
    return out


def summary(diffs: list[float]) -> str:
    """Mean ± standard error (runs above zero / runs)."""
    n = len(diffs)
    if n < 2:
        return "–"
    mean = sum(diffs) / n
    se = math.sqrt(sum((x - mean) ** 2 for x in diffs) / (n - 1) / n)
    return f"{mean:+.2f} ± {se:.2f} ({sum(x > 0 for x in diffs)}/{n})"


def paired(runs: dict[Key, dict], a: str, b: str, scenes: list[str]) -> list[float]:
    return [runs[(s, a, k)]["psnr"] - runs[(s, b, k)]["psnr"] for s in scenes for k in (0, 1)
            if (s, a, k) in runs and (s, b, k) in runs]


def say(line: str) -> None:
    sys.stdout.write(line + "\n")


def main(argv: list[str]) -> None:
    what, folders = argv[0], argv[1].split(",")
    if what == "cost":
        runs = load(folders, {r.split("/")[-3] for r in glob.glob(f"{folders[0]}/runs/*/*/")})
        variants = argv[2].split(",")
        keys = {(s, k) for s, _, k in runs}
        keys = {x for x in keys if all((x[0], v, x[1]) in runs for v in variants)}
        for v in variants:
            ev = [e for s, k in keys for e in runs[(s, v, k)]["events"]]
            wall = sum(e["select_wall_ms"] for e in ev) / len(ev)
            cpu = sum(e["select_cpu_ms"] for e in ev) / len(ev)
            say(f"{v}: wall {wall:.1f} ms, CPU {cpu:.1f} ms ({len(keys)} runs)")
        return
    scenes = argv[2].split(",")
    runs = load(folders, set(scenes))
    if what == "paired":
        for pair in argv[3].split(","):
            a, b = pair.split(":")
            say(f"{a} − {b}: {summary(paired(runs, a, b, scenes))}")
    elif what == "scenes":
        say("| method | " + " | ".join(scenes) + " | mean over scenes |")
        for v in argv[3].split(","):
            means = [sum(x) / len(x) for s in scenes
                     if (x := [runs[(s, v, k)]["psnr"] for k in (0, 1) if (s, v, k) in runs])]
            say(f"| {v} | " + " | ".join(f"{m:.2f}" for m in means)
                  + f" | {sum(means) / len(means):.2f} |")


if __name__ == "__main__":
    main(sys.argv[1:])

"""The `cpu_long` campaign's table from its run records: per-scene mean PSNR of Random,
AGILE-GS and AGILE-GS+, their paired differences, redundancy and the probes' wins, per seed
too. A lab script of ../2026-11-27-many-views.md (commit c46ad21).

    python notebook/2026-11-27-many-views/long_table.py RUNS_OUT_DIR
"""

from __future__ import annotations

import json
import math
import statistics
import sys
from pathlib import Path
from typing import Any

from agilegs.service.bench.redundancy import summarise_redundancy

SCENES = ["plant", "boot", "bob", "fish", "koala", "penguin", "floor", "skull", "spot",
          "stanford_bunny", "teapot", "violin"]
METHODS = {"random": "Random", "agile": "AGILE-GS", "agile_plus": "AGILE-GS+"}


def paired(rec: dict[str, dict[tuple[str, str], Any]], a: str, b: str,
           seed: str | None = None) -> str:
    keys = sorted(k for k in set(rec[a]) & set(rec[b]) if seed is None or k[1] == seed)
    d = [rec[a][k]["psnr"] - rec[b][k]["psnr"] for k in keys]
    se = statistics.stdev(d) / math.sqrt(len(d))
    return f"{statistics.fmean(d):+.2f} ± {se:.2f} ({sum(x > 0 for x in d)}/{len(d)})"


def main() -> None:
    root = Path(sys.argv[1]) / "runs"
    rec: dict[str, dict[tuple[str, str], Any]] = {m: {} for m in METHODS}
    for m in METHODS:
        for s in SCENES:
            for f in sorted((root / s / m).glob("seed*.json")):
                rec[m][(s, f.stem)] = json.loads(f.read_text())
    out = ["| method | " + " | ".join(SCENES) + " | mean over scenes | runs | selection ms |",
           "|" + "---|" * (len(SCENES) + 4)]
    for m, name in METHODS.items():
        cells, means = [], []
        for s in SCENES:
            v = [r["psnr"] for (sc, _), r in rec[m].items() if sc == s]
            cells.append(f"{statistics.fmean(v):.2f}" if v else "–")
            means += [statistics.fmean(v)] if v else []
        lat = [statistics.fmean(e["latency_ms"]["total"] for e in r["events"])
               for r in rec[m].values()]
        out.append(f"| {name} | " + " | ".join(cells) + f" | {statistics.fmean(means):.2f} | "
                   f"{len(rec[m])} | {statistics.fmean(lat):,.0f} |")
    out.append("")
    for a, b in (("agile", "random"), ("agile_plus", "random"), ("agile_plus", "agile")):
        out.append(f"{METHODS[a]} − {METHODS[b]}: {paired(rec, a, b)}")
        for seed in ("seed0", "seed1"):
            if sum(1 for k in rec[a] if k[1] == seed and k in rec[b]) > 1:
                out.append(f"  {seed}: {paired(rec, a, b, seed)}")
    for m in METHODS:
        r = summarise_redundancy(list(rec[m].values()))
        out.append(f"{m}: " + ", ".join(f"{k} {v:.2f}" for k, v in r.items() if v is not None))
    sys.stdout.write("\n".join(out) + "\n")


if __name__ == "__main__":
    main()

"""The main table's layout for a `bench run --profile cpu` folder: ``python main_table.py OUT
SCENE...`` (per-scene mean PSNR over the seeds, the mean over scenes, selection ms, the full-pool
EIG's selection time over the method's; then the paired differences of the chosen rows)."""

from __future__ import annotations

import json
import math
import statistics
import sys
from pathlib import Path

NAMES = {"random": "Random", "fisherrf": "FisherRF", "cover": "COVER",
         "full_eig": "Full-pool EIG (ceiling)", "agile": "AGILE-GS", "agile_plus": "AGILE-GS+",
         "agile_at_paper": "AGILE-GS (paper)", "agile_plus_at_paper": "AGILE-GS+ (paper)",
         "agile_at_single": "AGILE-GS (one anchor)",
         "agile_plus_at_single": "AGILE-GS+ (one anchor)"}
ROWS = ("agile", "agile_plus", "agile_plus_at_paper", "full_eig", "fisherrf", "cover")
COLS = ("random", "fisherrf", "cover", "full_eig", "agile_at_single", "agile_plus_at_single",
        "agile_plus_at_paper")


def main(out: Path, scenes: list[str]) -> None:
    rec = {m: {} for m in NAMES}
    for f in out.glob("runs/*/*/seed*.json"):
        if f.parts[-3] in scenes and f.parts[-2] in rec:
            rec[f.parts[-2]][(f.parts[-3], f.stem)] = json.loads(f.read_text())
    sel = {m: statistics.fmean(statistics.fmean(e["latency_ms"]["total"] for e in r["events"])
                               for r in rec[m].values()) for m in NAMES if rec[m]}
    w = sys.stdout.write
    w("| method | " + " | ".join(scenes) + " | mean over scenes | selection ms | "
      "full EIG / method |\n" + "|---" * (len(scenes) + 4) + "|\n")
    for m, name in NAMES.items():
        if not rec[m]:
            continue
        per = [statistics.fmean(r["psnr"] for (s, _), r in rec[m].items() if s == sc)
               for sc in scenes]
        w(f"| {name} | " + " | ".join(f"{x:.2f}" for x in per)
          + f" | {statistics.fmean(per):.2f} | {sel[m]:,.0f} | {sel['full_eig'] / sel[m]:.1f}× |\n")
    w("\n| row − column | " + " | ".join(NAMES[c] for c in COLS) + " |\n"
      + "|---" * (len(COLS) + 1) + "|\n")
    for r in ROWS:
        w(f"| {NAMES[r]} − | " + " | ".join("–" if c == r else _pair(rec, r, c) for c in COLS)
          + " |\n")


def _pair(rec: dict, a: str, b: str) -> str:
    keys = sorted(set(rec[a]) & set(rec[b]))
    d = [rec[a][k]["psnr"] - rec[b][k]["psnr"] for k in keys]
    se = statistics.stdev(d) / math.sqrt(len(d))
    return f"{statistics.fmean(d):+.2f} ± {se:.2f} ({sum(x > 0 for x in d)}/{len(d)})"


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2:])

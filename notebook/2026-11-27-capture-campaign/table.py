"""The capture campaign's tables from its run records: ``python table.py OUT`` (OUT the
``--out`` folder of ``agilegs bench run``, or several runs' records copied under one
``OUT/runs/<scene>/<method>/seed<k>.json``)."""

from __future__ import annotations

import json
import math
import statistics
import sys
from pathlib import Path

NAMES = {"random": "Random", "cover": "COVER", "full_eig": "full-pool EIG",
         "agile": "AGILE-GS", "agile_plus": "AGILE-GS+"}


def main(out: Path) -> None:
    rec: dict[str, dict[tuple[str, str], dict]] = {m: {} for m in NAMES}
    for f in sorted(out.glob("runs/*/*/seed*.json")):
        scene, method = f.parts[-3], f.parts[-2]
        if method in rec:
            rec[method][(scene, f.stem)] = json.loads(f.read_text())
    scenes = sorted({s for r in rec.values() for s, _ in r})
    w = sys.stdout.write
    w("| method | " + " | ".join(scenes) + " | runs | selection ms | pick angle ° | "
      "index jump |\n" + "|---" * (len(scenes) + 5) + "|\n")
    for m, name in NAMES.items():
        if not rec[m]:
            continue
        cells = []
        for s in scenes:
            v = [r["psnr"] for (sc, _), r in rec[m].items() if sc == s]
            cells.append(f"{statistics.fmean(v):.2f} ({len(v)})" if v else "–")
        runs = list(rec[m].values())
        lat = statistics.fmean(statistics.fmean(e["latency_ms"]["total"] for e in r["events"])
                               for r in runs)
        ang = [r["redundancy"]["pick_angle_mean_deg"] for r in runs]
        jump = [r["mean_index_jump"] for r in runs if r.get("mean_index_jump") is not None]
        w(f"| {name} | " + " | ".join(cells) + f" | {len(runs)} | {lat:,.0f} | "
          f"{statistics.fmean(ang):.1f} | {statistics.fmean(jump):.1f} |\n")
    w("\n| row − Random | " + " | ".join(scenes) + " | all |\n" + "|---" * (len(scenes) + 2)
      + "|\n")
    for m, name in NAMES.items():
        if m == "random" or not rec[m]:
            continue
        cells = [_pair(rec, m, "random", s) for s in scenes]
        w(f"| {name} | " + " | ".join(cells) + f" | {_pair(rec, m, 'random', None)} |\n")
    w(f"\nAGILE-GS+ − COVER: {_pair(rec, 'agile_plus', 'cover', None)}; "
      f"AGILE-GS+ − AGILE-GS: {_pair(rec, 'agile_plus', 'agile', None)}\n")


def _pair(rec: dict, a: str, b: str, scene: str | None) -> str:
    keys = sorted(k for k in set(rec[a]) & set(rec[b]) if scene is None or k[0] == scene)
    d = [rec[a][k]["psnr"] - rec[b][k]["psnr"] for k in keys]
    if not d:
        return "–"
    se = statistics.stdev(d) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
    return f"{statistics.fmean(d):+.2f} ± {se:.2f} ({sum(x > 0 for x in d)}/{len(d)})"


if __name__ == "__main__":
    main(Path(sys.argv[1]))

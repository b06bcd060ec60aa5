"""Thin the structure-from-motion points of a capture made by sfm_capture.py, to keep a scene
folder small: keep the points seen by at least ``--min-track`` photographs, then a random
``--max-points`` of them (numpy seed ``--seed``), and rewrite the COLMAP text model in place
with only the 2-D points that observe a kept 3-D point (sfm_capture.compact). The cameras,
the poses and the photographs are not touched.

    python notebook/thin_sfm_points.py SCENE_DIR [--min-track 4] [--max-points 3000] [--seed 0]

pycolmap (4.2.1 made the scenes) is a tool for preparing data, not a dependency of the project.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sfm_capture import compact  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--min-track", type=int, default=4)
    ap.add_argument("--max-points", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    model_dir = args.scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(model_dir)
    ids = sorted(i for i, p in rec.points3D.items() if p.track.length() >= args.min_track)
    rng = np.random.default_rng(args.seed)
    keep = set(ids) if len(ids) <= args.max_points else set(
        int(i) for i in rng.choice(ids, size=args.max_points, replace=False))
    before = rec.num_points3D()
    for i in [i for i in rec.points3D if i not in keep]:
        rec.delete_point3D(i)
    errors = [p.error for p in rec.points3D.values()]
    sys.stdout.write(f"{before} points, {len(ids)} seen by >= {args.min_track} photographs; "
                     f"kept {rec.num_points3D()} (mean reprojection error "
                     f"{float(np.mean(errors)):.3f} px at the structure from motion's size)\n")
    rec.write_text(model_dir)
    compact(model_dir)


if __name__ == "__main__":
    main()

"""The tile walks of commit 34af141 against the tree's, interleaved in one process on the same
maps: median CPU ms of fwd, fwd+bwd and fisher (bench render's functions) per set of walks.
The measurement behind ../2026-11-27-tile-walk-helpers.md.

A lab script of the notebook, not maintained with the package: it imports private names of
the package as they were at commit 0c48031 (``render_bench._build``, ``_functions``, the
module ``nbv.backend``). OLDK is a folder holding a package ``oldkernels``: 34af141's
``service/nbv/kernels/walks.py`` and ``common.py`` and an empty ``__init__.py``.

    OMP_NUM_THREADS=1 python notebook/2026-11-27-tile-walk-helpers/walks_ab.py OLDK [ROUNDS]
"""

import statistics
import sys
import time

import torch

sys.path.insert(0, sys.argv[1])
import oldkernels.walks as OLD  # noqa: E402

from agilegs.service.bench.render_bench import _build, _functions  # noqa: E402
from agilegs.service.nbv import kernels as K  # noqa: E402
from agilegs.service.nbv.backend import set_kernel_threads  # noqa: E402

torch.set_num_threads(1)
set_kernel_threads(1)
NEW = {n: getattr(K, n) for n in ("composite_forward", "composite_backward", "fisher_tiles")}
SETS = {"before": {n: getattr(OLD, n) for n in NEW}, "after": NEW}


def use(which: str) -> None:
    for n, f in SETS[which].items():
        setattr(K, n, f)


rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 15
sys.stdout.write("| N | px | what | before (34af141) ms | after ms | after / before |\n"
                 "|---|---|---|---|---|---|\n")
for n, res in ((20000, 128), (20000, 256), (100000, 128), (100000, 256)):
    gm, cam = _build("service/data/scenes/plant/plant.splat", n, res)
    fns = {k: f for k, f in _functions(gm, cam).items() if k in ("fwd", "fwd_bwd", "fisher")}
    for which in SETS:  # warm-up (compiles on a first use)
        use(which)
        for f in fns.values():
            f()
    cpu: dict[tuple[str, str], list[float]] = {(w, k): [] for w in SETS for k in fns}
    for r in range(rounds):
        order = list(SETS) if r % 2 == 0 else list(SETS)[::-1]
        for k, f in fns.items():
            for w in order:
                use(w)
                c0 = time.process_time()
                f()
                cpu[(w, k)].append((time.process_time() - c0) * 1e3)
    for k in fns:
        b, a = statistics.median(cpu[("before", k)]), statistics.median(cpu[("after", k)])
        sys.stdout.write(f"| {n:,} | {res}² | {k} | {b:.1f} | {a:.1f} | {a / b:.3f} |\n")
        sys.stdout.flush()

"""numba or C++ for the tile compositing: the measurement behind ../2026-11-25-cpu-kernels.md.

A lab script of the notebook, not maintained with the package: it imports the package's
internals as they were at commit 473da52 (private names included: ``render_bench._build``,
the modules ``nbv.backend`` and ``nbv.kernel_ops``). To run it again, check out that commit.

Builds the plant subsampled to 20k Gaussians at 128² (the kernels' projection and binning),
then times the compositing forward (recording the composited pairs) and backward of
agilegs.service.nbv.kernels against composite.cpp (the same loops in C++, -O3 -march=native,
called through ctypes), interleaved, on 1 and 2 threads; checks that both give the same
images and gradients; and reports the C++ build and load times.

    python notebook/2026-11-25-cpu-kernels/compare.py [--scene ...] [--repeats 15]
"""

from __future__ import annotations

import argparse
import ctypes
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from agilegs.service.bench.render_bench import _build
from agilegs.service.nbv import backend as B
from agilegs.service.nbv import kernel_ops as O
from agilegs.service.nbv import kernels as K

HERE = Path(__file__).resolve().parent


def build_cpp(out_dir: Path) -> tuple[ctypes.CDLL, float, float]:
    so = out_dir / "composite.so"
    t0 = time.perf_counter()
    subprocess.run(["g++", "-O3", "-march=native", "-shared", "-fPIC", "-std=c++17",
                    str(HERE / "composite.cpp"), "-o", str(so)], check=True)
    t1 = time.perf_counter()
    lib = ctypes.CDLL(str(so))
    t2 = time.perf_counter()
    return lib, t1 - t0, t2 - t1


def ptr(a: np.ndarray) -> ctypes.c_void_p:
    assert a.flags.c_contiguous
    return ctypes.c_void_p(a.ctypes.data)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene",
                    default=str(HERE.parents[3] / "shared/data/scenes/plant/plant.splat"))
    ap.add_argument("--gaussians", type=int, default=20000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    lib, build_s, load_s = build_cpp(Path(tempfile.mkdtemp()))
    for f in (lib.composite_forward_f32, lib.composite_backward_f32):
        f.restype = None
    gm, cam = _build(args.scene, args.gaussians, args.size)
    res = args.size
    arrs = B._params(gm)
    camv = B._camera_vector(cam, gm.dtype, 0.01)
    m2, con, z, radii, col, op, cov = O._project_np(K, arrs, camv, 1)
    tiles = O._Tiles(m2, con, op, col, z, radii, cov, res, res, 8)
    hw = res * res
    n_tiles = tiles.offsets.shape[0] - 1
    rng = np.random.default_rng(0)
    g_col = rng.standard_normal((hw, 3)).astype(np.float32)
    g_a = rng.standard_normal(hw).astype(np.float32)
    g_d = rng.standard_normal(hw).astype(np.float32)
    bg = np.array([0.1, 0.2, 0.3], np.float32)

    def outputs() -> dict[str, np.ndarray]:
        pk, pp, pa = tiles.pair_buffers(True)
        return {"pk": pk, "pp": pp, "pa": pa, "npairs": np.zeros(n_tiles, np.int64),
                "col": np.empty((hw, 3), np.float32), "tf": np.empty(hw),
                "dacc": np.empty(hw, np.float32),
                "grads": np.zeros((tiles.rec.shape[0], 10))}

    def run_numba(o: dict[str, np.ndarray], nth: int) -> None:
        common = tiles.common()
        B._parallel(lambda part: K.composite_forward(
            *common, part, nth, tiles.slots, True, o["pk"], o["pp"], o["pa"], o["npairs"],
            o["col"], o["tf"], o["dacc"]), nth)
        B._parallel(lambda part: K.composite_backward(
            *common, part, nth, tiles.slots, o["pk"], o["pp"], o["pa"], o["npairs"], o["tf"],
            bg, g_col, g_a, g_d, o["grads"]), nth)

    def run_cpp(o: dict[str, np.ndarray], nth: int) -> None:
        rw = tiles.rec.shape[1]
        B._parallel(lambda part: lib.composite_forward_f32(
            ptr(tiles.offsets), ctypes.c_int64(n_tiles), ptr(tiles.rec), ctypes.c_int64(rw),
            ptr(tiles.rbox), ptr(tiles.xs), ptr(tiles.ys), res, res, 8, part, nth,
            ptr(tiles.slots), 1, ptr(o["pk"]), ptr(o["pp"]), ptr(o["pa"]), ptr(o["npairs"]),
            ptr(o["col"]), ptr(o["tf"]), ptr(o["dacc"])), nth)
        B._parallel(lambda part: lib.composite_backward_f32(
            ptr(tiles.offsets), ctypes.c_int64(n_tiles), ptr(tiles.rec), ctypes.c_int64(rw),
            ptr(tiles.xs), ptr(tiles.ys), res, res, 8, part, nth, ptr(tiles.slots),
            ptr(o["pk"]), ptr(o["pp"]), ptr(o["pa"]), ptr(o["npairs"]), ptr(o["tf"]), ptr(bg),
            ptr(g_col), ptr(g_a), ptr(g_d), ptr(o["grads"])), nth)

    a, b = outputs(), outputs()
    run_numba(a, 1)
    run_cpp(b, 1)
    out = sys.stdout.write
    out(f"max |numba - C++|: colour {np.abs(a['col'] - b['col']).max():.2e}, T_final "
        f"{np.abs(a['tf'] - b['tf']).max():.2e}, gradients "
        f"{np.abs(a['grads'] - b['grads']).max():.2e} (of {np.abs(a['grads']).max():.2e})\n")
    times: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for _ in range(args.repeats):
        for nth in (1, 2):
            for name, fn in (("numba", run_numba), ("C++", run_cpp)):
                o = outputs()
                c0, w0 = time.process_time(), time.perf_counter()
                fn(o, nth)
                times.setdefault((name, nth), []).append(
                    ((time.process_time() - c0) * 1e3, (time.perf_counter() - w0) * 1e3))
    out(f"composite forward + backward, {args.gaussians} Gaussians, {res}², median of "
        f"{args.repeats} interleaved rounds:\n")
    for (name, nth), v in sorted(times.items()):
        cpu = statistics.median(x[0] for x in v)
        wall = statistics.median(x[1] for x in v)
        out(f"  {name:6s} {nth} thread(s): CPU {cpu:6.1f} ms, wall {wall:6.1f} ms\n")
    out(f"C++ build (g++ -O3) {build_s:.2f} s, load (ctypes) {load_s * 1e3:.1f} ms\n")


if __name__ == "__main__":
    main()

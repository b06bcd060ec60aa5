"""``agilegs bench bigmap``: a server holding a session of a million Gaussians.

Densifies a scene (default: the plant, 113k Gaussians) to ``--gaussians`` as ``agilegs bench
latency`` does (:func:`agilegs.lab.bench.latency.densified`), writes it as a ``.splat``
in a temporary folder, starts ``agilegs serve`` (HTTP only, one torch thread, the mapper
off, the default limits unless ``--env`` sets others), creates a session with a ``--size``²
camera (and one placeholder Gaussian), uploads the splat (``set_gaussians``, the raw file),
sets a pool of ``--pool`` candidates on a sphere around the map, commits ``--views`` of
them, then selects once with every method. For each step it prints the server's answer (or
the refusal: its status, the limit it names and the estimate), the round trip, and the
server process's resident memory: before the step and its peak during the step
(``/proc/<pid>/status``: VmRSS, and VmHWM reset before each step through
``/proc/<pid>/clear_refs``).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["add_arguments", "run"]

log = logging.getLogger(__name__)

PLANT = Path(__file__).resolve().parents[1] / "scenes" / "plant" / "plant.splat"
METHODS = ("random", "spread", "cover", "fisherrf", "full_eig", "agile", "agile_plus")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--scene", default=str(PLANT), help=".splat / .ply scene to densify (default: the plant)")
    a("--gaussians", type=int, default=1_000_000, help="Gaussians of the session's map")
    a("--size", type=int, default=512, help="the session camera's width and height (px)")
    a("--pool", type=int, default=300, help="candidates in the pool")
    a("--views", type=int, default=3, help="candidates committed before the selections")
    a("--methods", default=",".join(METHODS), help="selection methods, comma-separated")
    a("--env", action="append", default=[], metavar="AGILEGS_X=VALUE",
      help="a server setting (repeatable), e.g. AGILEGS_MAX_SELECT_SECONDS=3600")
    a("--timeout", type=float, default=3600.0, help="seconds one request may take")
    a("--json", dest="json_out", help="also write the results here")


def proc_memory(pid: int) -> dict[str, float]:
    """VmRSS and VmHWM (MiB) of process ``pid`` (Linux /proc)."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) / 1024.0
    return out


def reset_peak(pid: int) -> None:
    """Reset process ``pid``'s VmHWM to its current RSS (where /proc allows)."""
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    except OSError:  # not Linux, or not allowed: the peak is then the process's so far
        pass


def _sphere_poses(centre: Any, radius: float, n: int) -> Any:
    """``n`` camera-to-world poses [n, 4, 4] (OpenCV axes) on a Fibonacci sphere of
    ``radius`` around ``centre``, looking at it."""
    import numpy as np

    out = []
    golden = np.pi * (3.0 - np.sqrt(5.0))
    for i in range(n):
        y = 1.0 - 2.0 * (i + 0.5) / n
        r = np.sqrt(1.0 - y * y)
        d = np.array([np.cos(golden * i) * r, y, np.sin(golden * i) * r])
        eye = centre + radius * d
        z = -d
        up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.95 else np.array([1.0, 0.0, 0.0])
        x = np.cross(up, z)
        x /= np.linalg.norm(x)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, eye
        out.append(m)
    return np.stack(out)


def run(args: argparse.Namespace) -> int:
    import httpx
    import numpy as np
    import torch

    from agilegs.lab.bench.latency import densified
    from agilegs.service.launch import ServerProcess
    from agilegs.service.nbv import GaussianMap

    logging.getLogger("httpx").setLevel(logging.WARNING)
    env = {"AGILEGS_TORCH_THREADS": "1", "AGILEGS_MAPPER": "0"}
    for item in args.env:
        key, sep, value = item.partition("=")
        if not sep or not key.startswith("AGILEGS_"):
            raise SystemExit(f"--env: expected AGILEGS_NAME=VALUE, got {item!r}")
        env[key] = value
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    results: dict[str, Any] = {"gaussians": args.gaussians, "size": args.size,
                               "pool": args.pool, "views": args.views, "env": env, "steps": {}}
    with tempfile.TemporaryDirectory(prefix="agilegs-bigmap-") as tmp:
        t = time.perf_counter()
        gmap = GaussianMap.load(args.scene)
        if args.gaussians > len(gmap):
            gmap = densified(gmap, args.gaussians, 0)
        elif args.gaussians < len(gmap):
            keep = np.sort(np.random.default_rng(0).permutation(len(gmap))[:args.gaussians])
            gmap = gmap.subset(torch.from_numpy(keep))
        splat = Path(tmp) / "map.splat"
        gmap.save(splat)
        means = gmap.means.detach().double().numpy()
        centre = np.median(means, axis=0)
        reach = float(np.quantile(np.linalg.norm(means - centre, axis=1), 0.9))
        del gmap, means
        log.info("map of %d Gaussians written in %.1f s", args.gaussians,
                 time.perf_counter() - t)
        srv = ServerProcess(Path(tmp) / "state", zenoh=False, env=env).start()
        assert srv.proc is not None
        pid = srv.proc.pid
        try:
            with httpx.Client(base_url=srv.url, timeout=args.timeout) as h:
                f = args.size / 2 / np.tan(np.radians(25))
                intr = {"fx": f, "fy": f, "cx": args.size / 2, "cy": args.size / 2,
                        "width": args.size, "height": args.size}
                poses = _sphere_poses(centre, 2.5 * reach, args.pool)

                def step(name: str, method: str, path: str, **kw: Any) -> httpx.Response:
                    before = proc_memory(pid)
                    reset_peak(pid)
                    t0 = time.perf_counter()
                    r = h.request(method, path, **kw)
                    dt = time.perf_counter() - t0
                    after = proc_memory(pid)
                    row: dict[str, Any] = {"status": r.status_code, "seconds": dt,
                                           "rss_before_mib": before["VmRSS"],
                                           "peak_mib": max(after["VmHWM"], before["VmRSS"])}
                    if r.status_code != 200:
                        err = r.json().get("error", {})
                        row.update(code=err.get("code"), limit=err.get("limit"),
                                   estimate=err.get("estimate"), message=err.get("message"))
                    results["steps"][name] = row
                    log.info("%s: %s in %.1f s", name, r.status_code, dt)
                    return r

                sid = "bigmap"
                bounds = {"min": (centre - reach).tolist(), "max": (centre + reach).tolist()}
                r = step("create_session", "POST", "/v1/sessions",
                         json={"id": sid, "intrinsics": intr, "bounds": bounds,
                               "init_gaussians": 1})
                if r.status_code != 200:
                    raise SystemExit(f"create_session refused: {r.text[:300]}")
                r = step("set_gaussians", "PUT", f"/v1/sessions/{sid}/gaussians",
                         content=splat.read_bytes(), params={"format": "splat"},
                         headers={"content-type": "application/octet-stream"})
                if r.status_code != 200:
                    raise SystemExit(f"set_gaussians refused: {r.text[:300]}")
                step("set_pool", "PUT", f"/v1/sessions/{sid}/pool",
                     json={"poses": [{"matrix": p.tolist()} for p in poses]})
                for i in range(args.views):
                    step(f"commit {i}", "POST", f"/v1/sessions/{sid}/views",
                         json={"candidate_id": int(i * args.pool // max(args.views, 1)),
                               "keep_in_pool": False})
                for method in methods:
                    step(f"select {method}", "POST", f"/v1/sessions/{sid}/select",
                         json={"method": method})
                state = h.get(f"/v1/sessions/{sid}").json()
                results["final"] = {"version": state["version"], "views": state["num_views"],
                                    "pool": state["pool_size"]}
        finally:
            srv.stop()
    _print(results)
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(results, indent=2))
    return 0


def _print(results: dict[str, Any]) -> None:
    out = sys.stdout
    out.write(f"\nagilegs bench bigmap: {results['gaussians']} Gaussians, "
              f"{results['size']}x{results['size']} px, pool {results['pool']}, "
              f"{results['views']} views\n\n")
    out.write(f"{'step':<20}{'status':>7}{'seconds':>10}{'RSS before':>12}{'peak':>10}  "
              "refusal\n")
    for name, r in results["steps"].items():
        why = ""
        if r["status"] != 200:
            est = r.get("estimate") or {}
            why = f"{r.get('code')} {r.get('limit') or ''}"
            if est:
                why += (f" (estimate {est.get('seconds', 0):.0f} s, "
                        f"{est.get('peak_bytes', 0) / 2**20:.0f} MiB)")
        out.write(f"{name:<20}{r['status']:>7}{r['seconds']:>10.2f}"
                  f"{r['rss_before_mib']:>8.0f} MiB{r['peak_mib']:>6.0f} MiB  {why}\n")
    out.flush()

"""``agilegs demo``: the closed loop on a bundled scene, over real HTTP.

The demo starts ``agilegs serve`` as a subprocess (127.0.0.1, a free port, HTTP only, its
state folder ``--out``/state, where the sessions stay for ``agilegs export``) and plays a
simulated robot written with the client SDK (:class:`agilegs.client.Client`):

1. The ground truth is a splat scene (``--scene spot`` or ``teapot``, bundled with the
   project, or a ``.splat`` / ``.ply`` path), subsampled; the robot renders every frame it
   "captures" from it (RGB as PNG, and depth). The candidate pool is a seeded human-like
   capture around the object (:func:`~agilegs.service.nbv.candidates.capture_pool`); the
   held-out test views lie on orbits between the pool's rings. With a posed capture as
   ``--scene`` (COLMAP, transforms.json, rosbag2) the robot replays it instead
   (:class:`~agilegs.lab.demo.capture_robot.CaptureRobot`): the pool is its frames, a chosen
   frame returns its photograph, the test views are its held-out frames.
2. Two sessions, AGILE-GS+ and Random, are created from the same initial RGB-D frames (the
   server initialises each map by back-projecting the depth and its mapper trains it), with
   the same pool (candidate ids = pool indices) and the same mapper settings.
3. Each event, for each method: ``select`` (commit) on the current map; the robot renders the
   ground-truth frame at the chosen pose and sends it (``add_observations`` on the committed
   view); the server's mapper trains ``steps_per_view`` steps on it in the background; the
   robot polls the session's state until the mapper is idle, downloads the map
   (``get_gaussians``) and computes the PSNR on the held-out views. One line per event and
   method: the chosen candidate, the selection's latency breakdown and the PSNR.
4. A summary table (printed and written as ``psnr.md``, with each method's mean selection time
   and where AGILE-GS+ stands against Random, computed from the run), ``psnr.png`` (test PSNR
   against views, both methods) and ``demo.json``
   in ``--out``, and the scene's attribution.

With ``--view`` a live browser view (:class:`~agilegs.service.viewer.live.SessionViewer`,
``pip install "agilegs[viewer]"``) follows the AGILE-GS+ session from the start, the robot
reporting its PSNR to it; after the last event the server and the page stay up (``--hold``
seconds, default until Ctrl-C), and ``--screenshot PNG`` writes a screenshot of the page.

The server is stopped (terminate, then kill) whatever happens. Sizes: 64x64 images, the
ground truth subsampled to 3000 Gaussians, a pool of 60, 8 test views, 3 initial views and
8 events; ``--quick`` is a reduced mode for tests (32x32, 2 events, seconds).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agilegs.lab.demo.report import METHODS, plot, summary
from agilegs.service.launch import ServerProcess

if TYPE_CHECKING:
    import numpy as np
    from rich.console import Console

    from agilegs.client import Client

__all__ = ["DemoSize", "FULL", "QUICK", "add_arguments", "attribution", "make_robot", "run"]

log = logging.getLogger(__name__)

STAGES: tuple[str, ...] = ("information", "anchor", "scoring", "leverage", "rerank", "total")


@dataclass(frozen=True)
class DemoSize:
    """How big the demo is.

    Args:
        width: image width and height in pixels.
        gt_gaussians: the ground truth is subsampled (seeded) to this many Gaussians.
        pool_size: candidate poses.
        test_count: held-out test views.
        initial_views: RGB-D frames each session starts from.
        init_gaussians: Gaussians the server back-projects from their depth.
        events: selection events per method.
        steps_per_view: mapper training steps per view sent.
        shortlist_size: N of AGILE-GS+.
        max_gaussians: cap of the mapper's map.
        densify_every: the mapper densifies every this many steps.
    """

    width: int = 64
    gt_gaussians: int = 3000
    pool_size: int = 60
    test_count: int = 8
    initial_views: int = 3
    init_gaussians: int = 1500
    events: int = 8
    steps_per_view: int = 50
    shortlist_size: int = 10
    max_gaussians: int = 3000
    densify_every: int = 50


FULL = DemoSize()
QUICK = DemoSize(width=32, gt_gaussians=400, pool_size=14, test_count=3, initial_views=2,
                 init_gaussians=250, events=2, steps_per_view=6, shortlist_size=4,
                 max_gaussians=500, densify_every=6)

EXPECT = ("What this run measures: per event and method, the view chosen, the selection's "
          "latency breakdown in ms and the PSNR on held-out views; at the end, the PSNR table "
          "(also written to psnr.md), each method's mean selection time, and at which events "
          "AGILE-GS+ is ahead of, level with or behind Random, all computed from this run. One "
          "run is noisy: docs/benchmarks.md has the paired figures over twelve scenes.")
"""What the demo shows, printed first."""

BACKGROUND = (1.0, 1.0, 1.0)
FOV_DEG = 50.0
ORBIT_SCALE = 2.6  # camera distance / the object's 98% radius (as the benchmark)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--scene", default="spot",
      help="spot or teapot (bundled), a .splat / .ply file, or a posed capture (a COLMAP "
           "model, a transforms.json or a rosbag2: the robot replays its photographs; "
           "docs/your-data.md) (default spot)")
    a("--events", type=int, default=None,
      help=f"selection events per method (default {FULL.events}; --quick {QUICK.events})")
    a("--steps-per-view", type=int, default=None,
      help=f"mapper steps per view (default {FULL.steps_per_view}; --quick "
           f"{QUICK.steps_per_view})")
    a("--out", default="agilegs-demo", help="folder for psnr.png, demo.json and the server "
                                            "log (default ./agilegs-demo)")
    a("--quick", action="store_true", help="reduced mode for tests: 32x32, 2 events, tiny")
    a("--seed", type=int, default=0, help="seed of the pool, the subsample and the selectors")
    a("--server-threads", type=int, default=1,
      help="torch threads of the server (default 1: this process and the server share the "
           "machine)")
    a("--view", action="store_true",
      help='open a live browser view of the AGILE-GS+ session (pip install "agilegs[viewer]")')
    a("--view-port", type=int, default=8080, help="port of the view's page (default 8080)")
    a("--hold", type=float, default=None, metavar="S",
      help="with --view: keep the server and the page up S seconds after the last event "
           "(default: until Ctrl-C)")
    a("--screenshot", metavar="PNG",
      help="with --view: a screenshot of the page (headless chromium) after the last event")


# ============================================================================ helpers
def attribution(scene: str) -> str:
    """The attribution line of a bundled scene (its row of ``scenes/README.md``), or a note
    for a scene file of one's own."""
    from agilegs.lab.scenes import bundled_scene

    if scene not in ("spot", "teapot"):
        return _repository_scene(scene) or (f"Scene {scene}: not bundled; see its source "
                                             "for its licence.")
    file = bundled_scene(scene)
    text = (file.parent.parent / "README.md").read_text(encoding="utf-8")
    row = next((ln for ln in text.splitlines() if f"`{file.name}`" in ln), "")
    cells = [c.strip() for c in row.strip().strip("|").split("|")]
    credit = next((ln.strip() for ln in text.splitlines() if ln.startswith("Gaussian splats by")),
                  "")
    tail = text.split(credit, 1)[1].split("\n\n", 1)[0] if credit else ""
    credit = " ".join((credit + " " + tail.replace("\n", " ")).split())
    credit = credit.split(" licensed per object", 1)[0].rstrip(",") + "."
    if len(cells) >= 6:
        return f"Scene: {cells[5]} ({cells[4]}). {credit}".strip()
    return f"Scene: {file.name}. {credit}".strip()


def _repository_scene(scene: str) -> str | None:
    """The attribution of a scene of ``lab/scenes`` given as a path (its row of the folder's
    README: source and licence), or None for a path elsewhere."""
    import agilegs.lab.scenes as scenes

    root = Path(scenes.__file__).parent.resolve()
    try:
        name = Path(scene).resolve().relative_to(root).parts[0]
    except (ValueError, IndexError):
        return None
    text = (root / "README.md").read_text(encoding="utf-8")
    row = next((ln for ln in text.splitlines() if ln.startswith(f"| `{name}` |")), None)
    cells = [c.strip() for c in (row or "").strip().strip("|").split("|")]
    if len(cells) < 6:
        return None
    import re

    credit = re.sub(r"\[[^\]]+\]\(([^)]+)\)", r"lab/scenes/\1", cells[5])  # changes made
    return f"Scene {name} (in this repository, lab/scenes/{name}): {credit}. Licence {cells[4]}."


# ============================================================================ the robot
class Robot:
    """The simulated robot: it owns the ground truth and renders the frames it captures."""

    def __init__(self, scene: str, size: DemoSize, seed: int) -> None:
        import torch

        from agilegs.lab.bench.scene_model import orbit_cameras
        from agilegs.lab.bench.scenes import render_references
        from agilegs.lab.scenes import bundled_scene
        from agilegs.service.nbv import Intrinsics, load_scene
        from agilegs.service.nbv.candidates import capture_pool, scene_center_radius

        path = bundled_scene(scene) if scene in ("spot", "teapot") else Path(scene)
        if not path.exists():
            raise ValueError(f"--scene: {scene} is neither spot, teapot nor a file")
        self.gt = load_scene(path, max_gaussians=size.gt_gaussians, seed=seed)
        center, r98 = scene_center_radius(self.gt.means)
        self.radius = ORBIT_SCALE * r98
        self.intrinsics = Intrinsics.from_fov(FOV_DEG, size.width, size.width)
        self.pool = capture_pool(center, self.radius, size.pool_size, seed=seed)  # [D, 4, 4]
        test = orbit_cameras(center, self.radius, (20.0, 40.0), size.test_count)
        self.test_poses = test
        self.test_images, _ = render_references(self.gt, test, self.intrinsics, BACKGROUND)
        self.render_references = render_references
        self._torch = torch
        self.summary = f"{self.gt.num_gaussians} Gaussians"

    def capture(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 [H, W, 3] and depth float32 [H, W] (0: background) at ``pose`` [4, 4]."""
        import numpy as np

        torch = self._torch
        rgb, depth = self.render_references(
            self.gt, torch.from_numpy(np.asarray(pose, dtype=np.float32))[None],
            self.intrinsics, BACKGROUND)
        img = (rgb[0].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        return img, depth[0].numpy().astype(np.float32)

    def observation(self, pose: np.ndarray, **where: Any) -> Any:
        from agilegs.schemas import ObservationIn

        img, depth = self.capture(pose)
        return ObservationIn.from_numpy(None if where else pose, image=img, depth=depth,
                                        image_encoding="png", **where)

    def psnr(self, arrays: dict[str, np.ndarray]) -> float:
        """Mean PSNR (dB) of a downloaded map on the held-out test views."""
        from agilegs.service.mapper.quality import psnr
        from agilegs.service.nbv import Camera, GaussianMap, render

        torch = self._torch
        gmap = GaussianMap(**{k: torch.from_numpy(v.copy()) for k, v in arrays.items()})
        bg = torch.tensor(BACKGROUND, dtype=gmap.dtype)
        vals = []
        with torch.no_grad():
            for i in range(self.test_poses.shape[0]):
                out = render(gmap, Camera(c2w=self.test_poses[i], intrinsics=self.intrinsics),
                             background=bg)
                vals.append(psnr(out.rgb.clamp(0, 1), self.test_images[i]))
        return float(sum(vals) / len(vals))


def make_robot(scene: str, size: DemoSize, seed: int, work_dir: Path) -> tuple[Any, DemoSize]:
    """The robot for ``--scene`` and the demo's size fitted to it: a splat scene's rendering
    :class:`Robot`, or a :class:`~agilegs.lab.demo.capture_robot.CaptureRobot` that replays a
    posed capture, whose pool and test views are the capture's (the events capped at half the
    frames left after the initial views, so that the methods have a choice to make; its
    starting map is written to ``work_dir``). An empty folder is refused naming every layout
    a scene may have."""
    from agilegs.lab.demo.capture_robot import CaptureRobot, is_capture, load_capture

    if not is_capture(scene):
        if Path(scene).is_dir():  # no capture: a splat file, or the error naming every layout
            from agilegs.lab.bench.scenes import detect_scene_kind

            detect_scene_kind(scene)
        return Robot(scene, size, seed), size
    sc = load_capture(scene, size.width, size.test_count, seed, size.init_gaussians)
    if sc.pool_size < size.initial_views + 1:
        raise ValueError(f"--scene: the capture's pool ({sc.pool_size} frames) is smaller than "
                         f"{size.initial_views} initial views and one event")
    robot = CaptureRobot(sc, work_dir, size.init_gaussians, seed)
    fitted = replace(size, pool_size=sc.pool_size, test_count=int(sc.test_poses.shape[0]),
                     width=sc.intrinsics.width,
                     events=min(size.events, max(1, (sc.pool_size - size.initial_views) // 2)))
    return robot, fitted


def session_id(method: str) -> str:
    """The demo's session of a method (``demo-agile-plus``)."""
    return f"demo-{method.replace('_', '-')}"


def initial_indices(pool_size: int, count: int) -> list[int]:
    """``count`` pool indices spread evenly in capture order."""
    step = pool_size / count
    return sorted({min(pool_size - 1, int(step * (i + 0.5))) for i in range(count)})


def mapper_options(size: DemoSize, robot: Robot) -> dict[str, Any]:
    """The sessions' MapperOptions: the benchmark's small CPU recipe, scaled to the demo."""
    pos = robot.pool[:, :3, 3]
    extent = 1.1 * float((pos - pos.mean(0)).norm(dim=1).max())
    total = size.steps_per_view * (size.initial_views + size.events)
    return {
        "steps_per_view": size.steps_per_view,
        "config": {
            "background": list(getattr(robot, "background", BACKGROUND)),
            "sh_degree": 0,
            "sh_degree_interval": None,
            "densify_from": size.densify_every,
            "densify_every": size.densify_every,
            "densify_until": max(size.densify_every, total - 2 * size.steps_per_view),
            "opacity_reset_every": None,
            "prune_large_from": None,
            "init_stride": 2,
            "max_gaussians": size.max_gaussians,
            "lr_means_steps": max(1, total),
            "scene_extent": max(extent, 1e-6),
            "seed": 0,
        },
    }


def wait_idle(client: Client, sids: list[str], timeout: float = 900.0) -> dict[str, Any]:
    """Poll until every session's mapper is idle; their states."""
    deadline = time.monotonic() + timeout
    states: dict[str, Any] = {}
    while True:
        for sid in sids:
            st = client.get_session(sid).mapper
            assert st is not None
            if st.state == "error":
                raise RuntimeError(f"the mapper of {sid} failed: {st.error}")
            states[sid] = st
        if all(s.state in ("idle", "off") for s in states.values()):
            return states
        if time.monotonic() > deadline:
            raise TimeoutError(f"the mapper did not finish in {timeout:.0f} s")
        time.sleep(0.1)


def latency_text(latency: dict[str, float], server_ms: float | None) -> str:
    parts = [f"{k} {latency[k]:7.1f}" for k in STAGES if k in latency]
    server = f"{server_ms:7.1f}" if server_ms is not None else "   n/a"
    return "  ".join(parts) + f"  server {server} ms"


# ============================================================================ the loop
def run(args: argparse.Namespace) -> int:
    import torch

    torch.set_num_threads(1)  # the server runs beside us on a small machine
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request otherwise
    from rich.console import Console

    console = Console(highlight=False)
    size = QUICK if args.quick else FULL
    try:
        if args.events is not None:
            if args.events < 0:
                raise ValueError(f"--events must be >= 0, got {args.events}")
            size = replace(size, events=int(args.events))
        if args.steps_per_view is not None:
            if args.steps_per_view < 1:
                raise ValueError(f"--steps-per-view must be >= 1, got {args.steps_per_view}")
            size = replace(size, steps_per_view=int(args.steps_per_view))
        if args.server_threads < 1:
            raise ValueError(f"--server-threads must be >= 1, got {args.server_threads}")
        if size.pool_size - size.initial_views < size.events:
            raise ValueError(f"--events: the pool ({size.pool_size}) cannot give {size.events} "
                             f"events after {size.initial_views} initial views")
        if (args.screenshot or args.hold is not None) and not args.view:
            raise ValueError("--screenshot and --hold go with --view")
        if args.view:
            from agilegs.service.viewer.extra import require_viser

            require_viser()
            logging.getLogger("websockets").setLevel(logging.WARNING)  # viser's chatter
        t_start = time.perf_counter()
        robot, size = make_robot(args.scene, size, int(args.seed), Path(args.out))
    except (ValueError, OSError, RuntimeError) as exc:  # RuntimeError: the viewer's extra
        console.print(f"agilegs demo: {exc}", soft_wrap=True, markup=False)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    console.print(f"[bold]agilegs demo[/bold]: scene {args.scene} ({robot.summary}), "
                  f"{robot.intrinsics.width}x{robot.intrinsics.height} images, "
                  f"pool {size.pool_size}, "
                  f"{size.test_count} test views, {size.initial_views} initial views, "
                  f"{size.events} events, {size.steps_per_view} mapper steps per view",
                  soft_wrap=True)
    console.print(EXPECT, soft_wrap=True)
    server = ServerProcess(
        out / "state", zenoh=False, log_path=out / "server.log",
        args=["--log-level", "warning"],
        env={"AGILEGS_TORCH_THREADS": str(args.server_threads), "AGILEGS_MAPPER": "1",
             "AGILEGS_MAPPER_BURST": "10"})
    try:
        server.start(timeout=120.0)
        console.print(f"server: {server.url} (pid {server.proc.pid if server.proc else '?'}"
                      f", log {out / 'server.log'})", soft_wrap=True)
        ready = server.wait_ready(timeout=1800.0)  # its kernels compiled before the first event
        console.print(f"server ready in {ready:.1f} s more (its kernels compiled, or loaded "
                      "from numba's cache)", soft_wrap=True)
        results = closed_loop(server.url, robot, size, int(args.seed), console,
                              view=args if args.view else None)
    except Exception as exc:
        log.error("demo failed: %s", exc)
        tail = server.log()[-3000:]
        if tail:
            console.print(f"[dim]server log (tail):[/dim]\n{tail}", soft_wrap=True,
                          markup=False)
        return 1
    finally:
        server.stop()
    wall = time.perf_counter() - t_start
    results.update(scene=args.scene, size=asdict(size), seed=int(args.seed), wall_s=wall,
                   attribution=attribution(args.scene))
    (out / "psnr.md").write_text(summary(console, results))
    png = plot(results, out / "psnr.png")
    (out / "demo.json").write_text(json.dumps(results, indent=2))
    console.print(f"table: {out / 'psnr.md'}\nplot: {png}\nresults: {out / 'demo.json'}",
                  soft_wrap=True)
    sid = session_id("agile_plus")
    console.print(f"export (the map; the views as a nerfstudio and COLMAP dataset):\n"
                  f"  agilegs export {sid} {out / 'map.ply'} --state-dir {out / 'state'}\n"
                  f"  agilegs export {sid} {out / 'dataset'} --state-dir {out / 'state'}",
                  soft_wrap=True, markup=False)
    console.print(results["attribution"], soft_wrap=True)
    console.print(f"done in {wall:.1f} s", soft_wrap=True)
    return 0


def closed_loop(url: str, robot: Robot, size: DemoSize, seed: int, console: Console,
                view: argparse.Namespace | None = None) -> dict[str, Any]:
    """The robot's side over HTTP; returns the per-method curves and events. ``view``:
    the ``--view`` options (a live view of the AGILE-GS+ session)."""
    from contextlib import ExitStack

    from agilegs.client import Client

    with ExitStack() as stack:
        viewer = None
        if view is not None:
            from agilegs.service.viewer.live import SessionViewer

            viewer = stack.enter_context(SessionViewer(
                stack.enter_context(Client(url)), session_id("agile_plus"), port=view.view_port,
                where=url)).start(poll=0.5)
            console.print(f"view: {viewer.url} (AGILE-GS+)", soft_wrap=True)
        results = _loop(url, robot, size, seed, console, viewer)
        if viewer is not None and _hold(Client(url), viewer, view, console):  # type: ignore[arg-type]
            return results  # Ctrl-C stopped the server too: nothing left to delete
    return results  # the sessions stay in the state folder, for agilegs export


def _hold(client: Client, viewer: Any, view: argparse.Namespace, console: Console) -> bool:
    """After the last event: let the view catch up, write its screenshot, keep it up;
    whether Ctrl-C ended it."""
    with client:
        version = client.get_session(session_id("agile_plus")).version
    viewer.wait_until(lambda v: v.info is not None and v.info.version >= version, 30.0)
    if view.screenshot:
        from agilegs.service.viewer.browser import capture, write_png

        write_png(view.screenshot, capture(viewer.url))
        console.print(f"screenshot: {view.screenshot}", soft_wrap=True)
    if view.hold is None:
        console.print(f"view: {viewer.url} stays up; Ctrl-C to end", soft_wrap=True)
    try:
        time.sleep(view.hold if view.hold is not None else 10.0 ** 9)
    except KeyboardInterrupt:
        return True
    return False


def _loop(url: str, robot: Robot, size: DemoSize, seed: int, console: Console,
          viewer: Any) -> dict[str, Any]:
    from contextlib import suppress

    from agilegs.client import Client, NotFoundError

    intr = robot.intrinsics
    intrinsics = {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                  "width": intr.width, "height": intr.height}
    pool = robot.pool.double().numpy()
    initial = initial_indices(size.pool_size, size.initial_views)
    remaining = [i for i in range(size.pool_size) if i not in initial]
    frames = [robot.observation(pool[i]) for i in initial]
    sids = {key: session_id(key) for key, _ in METHODS}
    results: dict[str, Any] = {"methods": {}, "initial_views": initial}
    with Client(url, timeout=600.0) as c:
        for key, _name in METHODS:
            with suppress(NotFoundError):  # the last run's
                c.delete_session(sids[key])
            c.create_session(intrinsics, id=sids[key], frames=frames,
                             gaussians=getattr(robot, "initial_gaussians", None),
                             init_gaussians=size.init_gaussians, seed=seed,
                             defaults={"method": key, "shortlist_size": size.shortlist_size,
                                       "seed": seed},
                             mapper=mapper_options(size, robot))
            c.set_pool(sids[key], pool[remaining], ids=remaining)
            results["methods"][key] = {"curve": [], "events": []}
        t0 = time.perf_counter()
        wait_idle(c, list(sids.values()))
        console.print(f"initial maps trained ({size.initial_views * size.steps_per_view} steps "
                      f"each) in {time.perf_counter() - t0:.1f} s", soft_wrap=True)
        for key, name in METHODS:
            p = robot.psnr(c.get_gaussians(sids[key]).to_numpy())
            results["methods"][key]["curve"].append({"views": size.initial_views, "psnr": p})
            if viewer is not None and key == "agile_plus":
                viewer.report_psnr(size.initial_views, p)
            console.print(f"event 0  {name:<9}  {size.initial_views} initial views"
                          f"{'':>49}  PSNR {p:6.2f} dB", soft_wrap=True)
        for event in range(1, size.events + 1):
            decisions = {key: c.select(sids[key], method=key, commit=True) for key, _ in METHODS}
            for key, _ in METHODS:  # the robot drives there, captures, sends the frame
                d = decisions[key]
                assert d.committed is not None
                c.add_observations(sids[key], robot.observation(
                    d.chosen.pose.to_matrix(), view_id=d.committed.id))
            states = wait_idle(c, list(sids.values()))
            for key, name in METHODS:
                d = decisions[key]
                g = c.get_gaussians(sids[key])
                p = robot.psnr(g.to_numpy())
                views = size.initial_views + event
                rec = {"event": event, "views": views, "chosen": d.chosen.id,
                       "latency_ms": dict(d.latency_ms), "server_ms": d.server_ms,
                       "psnr": p, "gaussians": g.count,
                       "mapper_steps": states[sids[key]].steps}
                results["methods"][key]["events"].append(rec)
                results["methods"][key]["curve"].append({"views": views, "psnr": p})
                if viewer is not None and key == "agile_plus":
                    viewer.report_psnr(views, p)
                console.print(f"event {event}  {name:<9}  view #{d.chosen.id:<3}  "
                              f"{latency_text(d.latency_ms, d.server_ms)}  PSNR {p:6.2f} dB",
                              soft_wrap=True)
    return results

"""The options of the ``agilegs bench`` commands whose modules import torch, and the preamble
their ``run`` functions share.

``agilegs COMMAND --help`` and the parsing of a command line build only these parsers, so
that they answer without importing torch, FastAPI or matplotlib; each command module
exposes its function as ``add_arguments``. Everything here is standard library or
:mod:`agilegs.schemas` at import time (no torch); the preamble (:func:`int_list`,
:func:`str_list`, :func:`flag_values`, :func:`use_threads`, :func:`protocol_profile`) turns
the parsed options into values, a bad one into ``SystemExit`` with a line naming its flag.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from agilegs.lab.scenes import bundled_scene

if TYPE_CHECKING:
    from .profiles import Profile

__all__ = [
    "DEFAULT_CONFIGS",
    "PROFILE_NAMES",
    "add_latency_arguments",
    "add_proxy_arguments",
    "add_run_arguments",
    "add_value_arguments",
    "flag_values",
    "int_list",
    "protocol_profile",
    "str_list",
    "use_threads",
]

PROFILE_NAMES = ("capture", "cpu", "cpu_long", "paper", "tiny")
"""The profiles of :data:`agilegs.lab.bench.profiles.PROFILES`."""

DEFAULT_CONFIGS = ("default", "typical", "unconditioned", "point_zbuffer", "mixed_zbuffer")
"""The configurations ``agilegs bench proxy`` compares by default."""

_PROFILE_HELP = {
    "run": "paper: 10 initial views, +1 per 200 steps, 30K steps (GPU); cpu: 64x64, pool 180, "
           "4 initial, +1 per 50 steps to 12 views, 500 steps; cpu_long: 96x96, the whole "
           "ground truth, 10 initial, +1 per 50 steps to 40 views, 1800 steps; capture: a posed "
           "capture's own frames in order as the pool, 96 px wide, 10 initial, +1 per 50 steps "
           "to 40 views, 1600 steps; tiny: for tests",
    "other": "the protocol profile, as for bench run (default cpu)",
}


def _methods() -> tuple[str, ...]:
    from agilegs.config.selection import METHODS

    return METHODS


def add_latency_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--scene", default=str(bundled_scene("spot")),
      help="a .splat or .ply scene (default: the bundled Spot)")
    a("--pool", type=int, default=200, help="candidate pool size D (default 200)")
    a("--shortlist", type=int, default=10, help="shortlist size N (default 10)")
    a("--width", type=int, default=128, help="image width in pixels (default 128)")
    a("--height", type=int, default=128, help="image height in pixels (default 128)")
    a("--fov", type=float, default=50.0, help="horizontal field of view, deg (default 50)")
    a("--max-gaussians", type=int, default=20000,
      help="subsample the scene to this many Gaussians (seeded; default 20000)")
    a("--events", type=int, default=3,
      help="selection events timed, one acquired view more per event (default 3)")
    a("--acquired", type=int, default=5, help="initial acquired views (default 5)")
    a("--orbit-scale", type=float, default=2.6,
      help="orbit radius / the scene's 98%% radius (default 2.6)")
    a("--lam", type=float, default=1e-6, help="lambda of Hhat (default 1e-6)")
    a("--seed", type=int, default=0, help="seed of the subsample, the pool and the methods")
    a("--threads", type=int, default=0, help="torch threads (0: default)")
    a("--device", default="cpu",
      help="where the map, Hhat and the pool live and the methods run: cpu (default) or cuda")
    a("--methods", default="all",
      help="comma-separated subset of methods/ablations/variants, or 'all', 'base' "
           "(the methods), 'fast' (all but the exact-psi variants)")
    a("--json", dest="json_out", default=None, help="write results here")


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    methods = ",".join(_methods())
    a = parser.add_argument
    a("--scene", action="append", required=True, metavar="PATH",
      help="a ground-truth splat (.splat/.ply or its folder), a transforms.json image set, a "
           "COLMAP model folder or a rosbag2 (a folder with metadata.yaml, or an .mcap file); "
           "repeat for several scenes")
    a("--bag-topics", default="", metavar="SPEC",
      help="the topics of rosbag2 scenes, e.g. image=/cam/color/image_raw,depth=none,pose=tf,"
           "world=map (default: found by type; see docs/ros2.md)")
    a("--methods", default=methods,
      help=f"comma-separated methods ({methods}) or variants (method@option, see "
           "agilegs.lab.bench.variants)")
    a("--profile", default="cpu", choices=PROFILE_NAMES, help=_PROFILE_HELP["run"])
    a("--seeds", default="0,1", help="comma-separated seeds")
    a("--out", required=True, metavar="DIR", help="output folder")
    a("--embodied", type=int, default=None, metavar="K",
      help="only the K nearest candidates to the current view are eligible (the paper's K = 5)")
    a("--shortlist-strategies", default="", metavar="LIST",
      help="shortlist ablation of AGILE-GS: any of leverage,knearest,topnorm,online")
    a("--shortlist-method", default="agile", choices=("agile", "agile_plus"),
      help="the method of the shortlist ablation (default agile, as the paper's table)")
    a("--budgets", default="", metavar="LIST",
      help="shortlist-budget ablation of AGILE-GS+, e.g. 5,10,20,50")
    a("--device", default="cpu", help="cpu or cuda (default cpu)")
    a("--threads", type=int, default=0,
      help="torch threads (0: the profile's: 1 for cpu and tiny)")
    g = parser.add_argument_group("profile overrides")
    g.add_argument("--initial-views", type=int, default=None, help="views before the first event")
    g.add_argument("--interval", type=int, default=None, help="steps between selections")
    g.add_argument("--steps", type=int, default=None, help="total training steps")
    g.add_argument("--view-budget", type=int, default=None, help="views in all")
    g.add_argument("--pool-size", type=int, default=None, help="candidate poses D")
    g.add_argument("--resolution", type=int, default=None, help="image width (and height)")
    g.add_argument("--max-gaussians", type=int, default=None, help="ground-truth subsample")
    g.add_argument("--shortlist-size", type=int, default=None, help="N")
    g.add_argument("--lam", type=float, default=None, help="λ of Ĥ")
    g.add_argument("--rasterizer", default=None, choices=("auto", "builtin", "gsplat"),
                   help="what trains the map (MapperConfig.rasterizer; default auto: gsplat on "
                        "a GPU where it loads)")
    a("--eig-mass", action="store_true",
      help="also record per event where the chosen view's EIG lies (near/far Gaussians, seen "
           "by many/few pool views; Ĥ computed for every method) and its target gain, for "
           "agilegs bench coverage; a run with it is another run than one without")
    a("--no-plots", action="store_true", help="skip the PNG plots")
    a("--estimate-only", action="store_true", help="print the wall-time estimate and stop")
    a("--report-only", action="store_true",
      help="run nothing: write the tables and plots from the runs already in --out (a run not "
           "there yet is left out and listed as missing)")


def _add_protocol_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that ``bench value`` and ``bench proxy`` share: the scenes, the protocol
    profile and seed, the method that drives the acquisitions."""
    a = parser.add_argument
    a("--scene", action="append", required=True, metavar="PATH",
      help="a scene as for bench run; repeat for several")
    a("--profile", default="cpu", choices=PROFILE_NAMES, help=_PROFILE_HELP["other"])
    a("--seed", type=int, default=0, help="seed of the protocol (default 0)")
    a("--driver", default="random", help="the method that acquires the views")


def add_value_arguments(parser: argparse.ArgumentParser) -> None:
    _add_protocol_arguments(parser)
    a = parser.add_argument
    a("--events", default="1,4,7",
      help="comma-separated events to measure (those past the schedule are skipped)")
    a("--candidates", type=int, default=24,
      help="candidates whose realised gain is measured per event")
    a("--horizon", type=int, default=None,
      help="training steps after adding a candidate (default: the profile's interval)")
    a("--json", dest="json_out", default=None, help="write results here")
    a("--plots", default=None, metavar="DIR", help="a PNG per scene here")


def add_proxy_arguments(parser: argparse.ArgumentParser) -> None:
    _add_protocol_arguments(parser)
    a = parser.add_argument
    a("--configs", default=",".join(DEFAULT_CONFIGS),
      help="comma-separated configurations: default, or agile variant options joined by + "
           "(e.g. typical+unconditioned)")
    a("--json", dest="json_out", default=None, help="write results here")


# ----------------------------------------------------------------------------- the preamble
def str_list(text: str) -> list[str]:
    """The non-empty items of a comma-separated option."""
    return [s.strip() for s in text.split(",") if s.strip()]


def int_list(text: str, flag: str) -> list[int]:
    """The integers of a comma-separated option; ``SystemExit`` naming ``flag`` otherwise."""
    with flag_values(flag):
        try:
            return [int(s) for s in str_list(text)]
        except ValueError:
            raise ValueError(f"expected comma-separated integers, got {text!r}") from None


@contextmanager
def flag_values(flag: str) -> Iterator[None]:
    """Turns a ``ValueError`` raised while reading ``flag``'s value into ``SystemExit``
    with a line ``FLAG: reason``."""
    try:
        yield
    except ValueError as exc:
        raise SystemExit(f"{flag}: {exc}") from None


def use_threads(threads: int) -> int:
    """torch's thread count set to ``threads`` (0: left as it is); the count in effect."""
    import torch

    if threads > 0:
        torch.set_num_threads(threads)
    return torch.get_num_threads()


def protocol_profile(args: argparse.Namespace) -> Profile:
    """The protocol profile of ``args.profile`` with the overrides the command has
    (:func:`~agilegs.lab.bench.profiles.resolve_profile`), and torch's threads set to
    ``--threads`` where the command has it and is not 0, else to the profile's."""
    from .profiles import resolve_profile

    profile = resolve_profile(args)
    use_threads(getattr(args, "threads", 0) or profile.threads or 0)
    return profile

"""agilegs.service.nbv: the maths of AGILE-GS (tensors in, tensors out; no I/O, no state).

The public face; every name below is defined in the module named beside it, and the code of
this project imports it from there:

- Gaussian maps and cameras: ``GaussianMap``, ``load_scene`` (:mod:`.gaussians`); ``Camera``,
  ``Intrinsics``, ``look_at``, ``check_pose`` (:mod:`.camera`).
- Rendering: ``render`` -> ``RenderResult`` (rgb [H,W,3], alpha [H,W], depth [H,W])
  (:mod:`.rasterize`); ``project_gaussians`` (:mod:`.projection`).
- Information (:mod:`.information`): ``fisher_diag``, ``fisher_diag_bruteforce``,
  ``init_information``, ``accumulate_information``, ``expected_information_gain``,
  ``trace_surrogate``, ``eig_scores``; Ĥ of a set of views ``information_of_views`` and one
  view's ``view_information`` (:mod:`.upkeep`).
- Poses (:mod:`.se3`): ``se3_exp``, ``se3_log``, ``hat``, ``vee``.
- Selection: ``select`` -> ``Selection``, ``METHODS`` (:mod:`.selectors`; the methods are
  registered by name in :mod:`.methods`), ``greedy_ridge_leverage`` (:mod:`.leverage`). Its
  settings, ``SelectConfig`` with ``AnchorConfig`` and ``ScoringConfig``, are
  :mod:`agilegs.config`'s.
"""

from __future__ import annotations

from .camera import Camera, Intrinsics, check_pose, look_at
from .gaussians import GaussianMap, load_scene
from .information import (
    accumulate_information,
    eig_scores,
    expected_information_gain,
    fisher_diag,
    fisher_diag_bruteforce,
    init_information,
    trace_surrogate,
)
from .leverage import greedy_ridge_leverage
from .projection import project_gaussians
from .rasterize import RenderResult, render
from .se3 import hat, se3_exp, se3_log, vee
from .selectors import METHODS, Selection, select
from .upkeep import information_of_views, view_information

__all__ = [
    "METHODS",
    "Camera",
    "GaussianMap",
    "Intrinsics",
    "RenderResult",
    "Selection",
    "accumulate_information",
    "check_pose",
    "eig_scores",
    "expected_information_gain",
    "fisher_diag",
    "fisher_diag_bruteforce",
    "greedy_ridge_leverage",
    "hat",
    "information_of_views",
    "init_information",
    "load_scene",
    "look_at",
    "project_gaussians",
    "render",
    "se3_exp",
    "se3_log",
    "select",
    "trace_surrogate",
    "vee",
    "view_information",
]

"""agilegs.service.nbv: the maths of AGILE-GS (tensors in, tensors out; no I/O, no state).

Public surface (imported lazily, so ``import agilegs.service.nbv`` stays cheap):

- Gaussian maps and cameras: ``GaussianMap``, ``Camera``, ``Intrinsics``, ``look_at``.
- Rendering: ``render`` -> ``RenderResult`` (rgb [H,W,3], alpha [H,W], depth [H,W]).
- Information: ``fisher_diag``, ``init_information``, ``accumulate_information``,
  ``expected_information_gain``, ``trace_surrogate``; Hhat of a set of views
  ``information_of_views`` and one view's ``view_information``.
- Poses: ``se3_exp``, ``se3_log``, ``hat``, ``vee``.
- Selection: ``select`` -> ``Selection`` (``select_validated`` for inputs validated already),
  ``SelectConfig`` (with ``AnchorConfig``,
  ``ScoringConfig``), ``eig_scores``, ``greedy_ridge_leverage``; the methods are registered
  by name in :mod:`agilegs.service.nbv.methods`.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS: dict[str, str] = {
    "GaussianMap": "gaussians",
    "FIELD_NAMES": "gaussians",
    "load_scene": "gaussians",
    "Camera": "camera",
    "Intrinsics": "camera",
    "look_at": "camera",
    "check_pose": "camera",
    "render": "rasterize",
    "RenderResult": "rasterize",
    "project_gaussians": "projection",
    "fisher_diag": "information",
    "fisher_diag_bruteforce": "information",
    "init_information": "information",
    "accumulate_information": "information",
    "expected_information_gain": "information",
    "trace_surrogate": "information",
    "information_of_views": "upkeep",
    "view_information": "upkeep",
    "se3_exp": "se3",
    "se3_log": "se3",
    "hat": "se3",
    "vee": "se3",
    "greedy_ridge_leverage": "leverage",
    "select": "selectors",
    "select_validated": "selectors",
    "Selection": "selectors",
    "SelectConfig": "selectors",
    "AnchorConfig": "selectors",
    "ScoringConfig": "selectors",
    "METHODS": "selectors",
    "eig_scores": "information",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__

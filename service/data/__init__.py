"""Bundled data: the demo's two ground-truth splat scenes (``scenes/spot``, ``scenes/teapot``,
credited in scenes/README.md) and their loader. The benchmark's other scenes sit beside them in
the repository and are not part of the package."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def bundled_scene(name: str = "spot") -> Path:
    """Path of a bundled ``.splat`` scene: ``"spot"`` (default) or ``"teapot"``."""
    files = {"spot": "spot_10k.splat", "teapot": "teapot_10k.splat"}
    if name not in files:
        raise ValueError(f"name must be one of {sorted(files)}, got {name!r}")
    return Path(str(resources.files(__package__) / "scenes" / name / files[name]))

"""The benchmark's scenes (credited in ``README.md`` beside this file) and the loader of the
demo's two, which ship in the package: ``spot`` and ``teapot``. The others stay in the
repository and are not part of the package."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def bundled_scene(name: str = "spot") -> Path:
    """Path of a bundled ``.splat`` scene: ``"spot"`` (default) or ``"teapot"``."""
    files = {"spot": "spot_10k.splat", "teapot": "teapot_10k.splat"}
    if name not in files:
        raise ValueError(f"name must be one of {sorted(files)}, got {name!r}")
    return Path(str(resources.files(__package__) / name / files[name]))

"""Tolerances of the geometry conventions, shared by the wire (which refuses a pose outside
them) and the maths (which checks the poses it is given against the same ones)."""

from __future__ import annotations

__all__ = ["MAX_COORD", "ORTHONORMAL_ATOL", "QUATERNION_NORM_ATOL"]

ORTHONORMAL_ATOL = 1e-3
"""Largest accepted ``max |R^T R - I|`` of a pose's rotation block."""
QUATERNION_NORM_ATOL = 1e-3
"""Largest accepted ``| ||q|| - 1 |`` of a pose quaternion."""
MAX_COORD = 1e6
"""Largest accepted absolute coordinate (pose translations, bounds), in scene units."""

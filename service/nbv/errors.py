"""The maths' refusal of a bad argument: a ValueError that names the argument."""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """``argument`` is malformed (its message says how); a ``ValueError``.

    Attributes:
        argument: the name of the offending argument (``"candidates"``, ``"current_pose"``).
    """

    def __init__(self, argument: str, message: str) -> None:
        super().__init__(message)
        self.argument = argument

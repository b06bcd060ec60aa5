"""The service's mapper, which lives with the sessions it serves:
:mod:`agilegs.service.sessions.trainer` (this name re-exports it)."""

from .sessions.trainer import SessionTrainer, Trainer, compose_src

__all__ = ["SessionTrainer", "Trainer", "compose_src"]

"""Frames from three topics: a colour image, a depth image and a camera pose that share a
``header.stamp``.

ROS 2 drivers stamp a camera's images (and its ``camera_info``) with the capture time, and a
robot stamps the camera pose it publishes for a frame with the image's stamp. The assembler
pairs the parts of a frame by that exact stamp, whatever the order they arrive in: a frame
is complete with its image and its pose, plus its depth image when the namespace expects
depth. At most :data:`MAX_PENDING` stamps wait; past that the oldest incomplete one is
dropped and reported with what it lacked. A part that arrives for a frame already complete
(a depth image the namespace does not wait for, a repeated message) is ignored.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

__all__ = ["MAX_PENDING", "PARTS", "Dropped", "FrameAssembler", "FrameParts"]

MAX_PENDING = 8
PARTS = ("image", "depth", "camera_pose")


@dataclass
class FrameParts:
    """The parts of one frame received so far (message objects, or None)."""

    stamp_ns: int
    image: Any = None
    depth: Any = None
    camera_pose: Any = None

    def missing(self, expect_depth: bool) -> list[str]:
        need = ("image", "depth", "camera_pose") if expect_depth else ("image", "camera_pose")
        return [p for p in need if getattr(self, p) is None]


@dataclass(frozen=True)
class Dropped:
    """An incomplete frame given up: its stamp and the parts it lacked."""

    stamp_ns: int
    missing: tuple[str, ...]


@dataclass
class FrameAssembler:
    """Pairs frame parts by stamp (see the module docstring)."""

    expect_depth: bool = False
    max_pending: int = MAX_PENDING
    pending: dict[int, FrameParts] = field(default_factory=dict)
    done: deque[int] = field(default_factory=lambda: deque(maxlen=4 * MAX_PENDING))

    def add(self, part: str, stamp_ns: int, message: Any) -> tuple[FrameParts | None,
                                                                    list[Dropped]]:
        """Add ``message`` as ``part`` of the frame at ``stamp_ns``; returns the frame if it
        is now complete (and forgets it), and the frames dropped to make room. A part that
        arrives twice for a stamp replaces the first."""
        if part not in PARTS:
            raise ValueError(f"unknown frame part {part!r}")
        if stamp_ns in self.done:
            return None, []
        parts = self.pending.get(stamp_ns)
        if parts is None:
            parts = self.pending[stamp_ns] = FrameParts(stamp_ns)
        setattr(parts, part, message)
        if not parts.missing(self.expect_depth):
            del self.pending[stamp_ns]
            self.done.append(stamp_ns)
            return parts, []
        dropped = []
        while len(self.pending) > self.max_pending:
            oldest = min(self.pending)
            gone = self.pending.pop(oldest)
            dropped.append(Dropped(oldest, tuple(gone.missing(self.expect_depth))))
        return None, dropped

    def clear(self) -> None:
        self.pending.clear()
        self.done.clear()

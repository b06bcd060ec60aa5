"""Frames from three topics: a colour image, its camera pose and a depth image.

ROS 2 camera drivers stamp an image (and its ``camera_info``) with its capture time, and the
robot stamps the camera pose it publishes for a frame with that image's stamp: the image and
the pose of a frame pair by the exact ``header.stamp``. A depth camera's registered depth
image (a RealSense's ``aligned_depth_to_color``) carries its own capture time, within a few
milliseconds of the colour image's: it pairs with the image whose stamp is nearest, within
:data:`DEPTH_SYNC_NS`. Parts pair whatever order they arrive in.

A frame is complete with its image and its pose, plus its depth image when the namespace
expects depth (without, a depth image that arrived in time joins the frame). At most
:data:`MAX_PENDING` frames wait, each at most :data:`FRAME_DEADLINE` seconds from its first
part's arrival; past either the oldest incomplete one is dropped (its parts freed) and
reported with what it lacked (:meth:`FrameAssembler.expire` drops the late ones when no part
arrives). A part for a frame already complete (a repeated message) is ignored.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

__all__ = ["DEPTH_SYNC_NS", "FRAME_DEADLINE", "MAX_PENDING", "PARTS", "Dropped",
           "FrameAssembler", "FrameParts"]

MAX_PENDING = 8
FRAME_DEADLINE = 10.0
"""Seconds an incomplete frame waits for its other parts (from its first part's arrival)."""
DEPTH_SYNC_NS = 20_000_000
"""Largest stamp difference of a depth image to its colour image (20 ms)."""
PARTS = ("image", "depth", "camera_pose")


@dataclass
class FrameParts:
    """The parts of one frame (keyed by the colour image's stamp) received so far."""

    stamp_ns: int
    image: Any = None
    depth: Any = None
    camera_pose: Any = None
    arrived: float = field(default_factory=time.monotonic)

    def missing(self, expect_depth: bool) -> list[str]:
        need = ("image", "camera_pose", "depth") if expect_depth else ("image", "camera_pose")
        return [p for p in need if getattr(self, p) is None]


@dataclass(frozen=True)
class Dropped:
    """An incomplete frame given up: its stamp and the parts it lacked."""

    stamp_ns: int
    missing: tuple[str, ...]


@dataclass
class FrameAssembler:
    """Pairs frame parts (see the module docstring)."""

    expect_depth: bool = False
    max_pending: int = MAX_PENDING
    sync_ns: int = DEPTH_SYNC_NS
    deadline: float = FRAME_DEADLINE
    pending: dict[int, FrameParts] = field(default_factory=dict)
    depths: dict[int, Any] = field(default_factory=dict)
    done: deque[int] = field(default_factory=lambda: deque(maxlen=4 * MAX_PENDING))

    def add(self, part: str, stamp_ns: int, message: Any) -> tuple[list[FrameParts],
                                                                    list[Dropped]]:
        """Add ``message`` as ``part`` stamped ``stamp_ns``; returns the frames now complete
        (forgotten here) and the frames dropped to make room."""
        if part not in PARTS:
            raise ValueError(f"unknown frame part {part!r}")
        if part == "depth":
            self.depths[stamp_ns] = (message, time.monotonic())
            while len(self.depths) > self.max_pending:
                del self.depths[min(self.depths)]
            return self._complete(sorted(self.pending)), self.expire()
        if stamp_ns in self.done:
            return [], self.expire()
        parts = self.pending.setdefault(stamp_ns, FrameParts(stamp_ns))
        setattr(parts, part, message)
        done = self._complete([stamp_ns])
        dropped = self.expire()
        while len(self.pending) > self.max_pending:
            oldest = min(self.pending)
            gone = self.pending.pop(oldest)
            dropped.append(Dropped(oldest, tuple(gone.missing(self.expect_depth))))
        return done, dropped

    def _complete(self, stamps: list[int]) -> list[FrameParts]:
        out = []
        for t in stamps:
            parts = self.pending.get(t)
            if parts is None or parts.image is None or parts.camera_pose is None:
                continue
            near = [d for d in self.depths if abs(d - t) <= self.sync_ns]
            if near:
                best = min(near, key=lambda d: (abs(d - t), d))
                parts.depth = self.depths.pop(best)[0]
            elif self.expect_depth:
                continue
            del self.pending[t]
            self.done.append(t)
            out.append(parts)
        return out

    def expire(self, now: float | None = None) -> list[Dropped]:
        """Drop the incomplete frames (and lone depth images) older than ``deadline``
        seconds at ``now`` (default: the monotonic clock); returns the frames dropped."""
        now = time.monotonic() if now is None else now
        late = sorted(t for t, p in self.pending.items() if now - p.arrived > self.deadline)
        out = []
        for t in late:
            gone = self.pending.pop(t)
            out.append(Dropped(t, tuple(gone.missing(self.expect_depth))))
        for t in [t for t, (_, at) in self.depths.items() if now - at > self.deadline]:
            del self.depths[t]
        return out

    def clear(self) -> None:
        self.pending.clear()
        self.depths.clear()
        self.done.clear()

"""What a session holds, as persisted: :class:`SessionRecord` (immutable; a change builds a
new one) and its acquired views, :class:`ViewRecord`; the names of the files in a session's
folder (see :mod:`agilegs.service.store.write` for the layout)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from torch import Tensor

from ..nbv import GaussianMap
from .integrity import FORMAT, ManifestError, decode_manifest

__all__ = ["MANIFEST", "PREVIOUS", "REQUIRED", "ROLES", "ROLE_FILE", "SESSION_NAME", "VIEWS",
           "AppliedRequest", "SessionRecord", "ViewRecord", "named_in", "view_id"]

ROLES = ("gaussians", "information", "pool", "warm")
"""The tensor files of a version, one per role."""
REQUIRED = ("gaussians", "information", "pool")
"""The roles a session cannot do without (``warm`` is a cache: losing it costs a cold start)."""
MANIFEST = "manifest.json"
PREVIOUS = "manifest.prev.json"
VIEWS = "views"
SESSION_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
ROLE_FILE = re.compile(r"^(gaussians|information|pool|warm)\.(\d+)\.pt$")
"""``<role>.<version>.pt``."""


def view_id(rel: str) -> int | None:
    """The view id of ``views/v00000003.rgb.png`` (None for another file)."""
    hit = re.match(rf"^{VIEWS}/v(\d+)\.", rel)
    return int(hit.group(1)) if hit else None


@dataclass(frozen=True)
class ViewRecord:
    """An acquired view as persisted."""

    id: int
    pose: np.ndarray  # [4, 4] float64, camera-to-world
    candidate_id: int | None
    created_at: float
    intrinsics: dict[str, Any] | None = None  # of the image
    image_file: str | None = None  # under views/
    image_encoding: str | None = None  # png | jpeg | raw
    depth_file: str | None = None
    depth_scale: float = 1.0

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "pose": self.pose.tolist(),
            "candidate_id": self.candidate_id,
            "created_at": self.created_at,
            "intrinsics": self.intrinsics,
            "image_file": self.image_file,
            "image_encoding": self.image_encoding,
            "depth_file": self.depth_file,
            "depth_scale": self.depth_scale,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ViewRecord:
        return cls(
            id=int(d["id"]),
            pose=np.asarray(d["pose"], dtype=np.float64),
            candidate_id=d.get("candidate_id"),
            created_at=float(d["created_at"]),
            intrinsics=d.get("intrinsics"),
            image_file=d.get("image_file"),
            image_encoding=d.get("image_encoding"),
            depth_file=d.get("depth_file"),
            depth_scale=float(d.get("depth_scale", 1.0)),
        )


@dataclass(frozen=True)
class AppliedRequest:
    """A write applied to the session under a request id (:mod:`agilegs.schemas.requests`):
    the operation, the version it made, and its answer as JSON-able data (None: not kept;
    the answer is made again from the session, or the request is too old)."""

    id: str
    op: str
    version: int
    answer: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "op": self.op, "version": self.version, "answer": self.answer}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> AppliedRequest:
        answer = d.get("answer")
        return cls(id=str(d["id"]), op=str(d["op"]), version=int(d["version"]),
                   answer=dict(answer) if answer is not None else None)


@dataclass(frozen=True)
class SessionRecord:
    """Everything a session holds. Never mutated in place: a change builds a new record."""

    id: str
    created_at: float
    updated_at: float
    version: int
    intrinsics: dict[str, Any]
    bounds: dict[str, Any] | None
    defaults: dict[str, Any]
    information_config: dict[str, Any]
    gmap: GaussianMap
    h_acc: dict[str, Tensor]
    pool_ids: np.ndarray  # [D] int64
    pool_poses: np.ndarray  # [D, 4, 4] float64
    next_candidate_id: int
    views: tuple[ViewRecord, ...]
    next_view_id: int
    warm_state: dict[str, Any] | None = None
    files: dict[str, str] = field(default_factory=dict)
    mapper: dict[str, Any] | None = None  # mapper options and progress (JSON, in the manifest)
    checksums: dict[str, str] = field(default_factory=dict)  # path in the folder -> checksum
    requests: tuple[AppliedRequest, ...] = ()  # the last writes applied under a request id

    def named_files(self) -> set[str]:
        """Every file this version names: role files, and ``views/<name>`` of its frames."""
        out = set(self.files.values())
        for v in self.views:
            out.update(f"{VIEWS}/{n}" for n in (v.image_file, v.depth_file) if n)
        return out

    def manifest(self) -> dict[str, Any]:
        named = self.named_files()
        return {
            "format": FORMAT,
            "id": self.id,
            "created_at": self.created_at,
            "updated_at": self.updated_at,
            "version": self.version,
            "intrinsics": self.intrinsics,
            "bounds": self.bounds,
            "defaults": self.defaults,
            "information_config": self.information_config,
            "next_candidate_id": self.next_candidate_id,
            "next_view_id": self.next_view_id,
            "views": [v.to_json() for v in self.views],
            "files": self.files,
            "mapper": self.mapper,
            "requests": [r.to_json() for r in self.requests],
            "checksums": {k: v for k, v in sorted(self.checksums.items()) if k in named},
        }


def named_in(manifest: bytes | None) -> set[str]:
    """The files a manifest's bytes name (none when they do not decode)."""
    if manifest is None:
        return set()
    try:
        m = decode_manifest(manifest)
    except ManifestError:
        return set()
    out = set(dict(m.get("files") or {}).values())
    for v in m.get("views") or []:
        out.update(f"{VIEWS}/{n}" for n in (v.get("image_file"), v.get("depth_file")) if n)
    return out

"""The persistent session store: every acknowledged state change is on disk first.

Layout under ``<state_dir>/sessions/<session>/``::

    manifest.json            small JSON: settings, counters, views, and the file names below
    gaussians.<v>.pt         the Gaussians (torch.save of the five tensors)
    information.<v>.pt       Ĥ per parameter block
    pool.<v>.pt              candidate ids [D] and poses [D, 4, 4]
    warm.<v>.pt              the selector's warm-start state after the last commit
    views/<id>.rgb.<ext>     images as sent (png / jpg) or as .npy
    views/<id>.depth.npy     depth as sent

A change writes its new files under fresh names (``<v>`` is the session version that wrote
them; a file is never overwritten), each to a temporary file that is fsynced and renamed;
then ``manifest.json`` is replaced the same way, which is the commit point; the folder is
fsynced; only then are the superseded files removed. A crash at any point leaves the old
manifest and its files, or the new ones; :meth:`SessionStore.load_all` removes whatever
no manifest names. Sessions are created in a hidden folder renamed into place, and deleted
by renaming them aside before removing them.
"""

from __future__ import annotations

import io
import json
import logging
import os
import shutil
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .nbv.gaussians import GaussianMap

__all__ = ["ROLES", "SessionRecord", "SessionStore", "StoreError", "ViewRecord"]

log = logging.getLogger(__name__)

FORMAT = 1
ROLES = ("gaussians", "information", "pool", "warm")
MANIFEST = "manifest.json"
VIEWS = "views"


class StoreError(RuntimeError):
    """The state folder could not be read or written."""


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

    def manifest(self) -> dict[str, Any]:
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
        }


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class SessionStore:
    """Session records on disk under ``root/sessions`` (see the module docstring)."""

    def __init__(self, root: Path | str, *, fsync: bool = True) -> None:
        self.root = Path(root)
        self.sessions_dir = self.root / "sessions"
        self.fsync = fsync
        self.sessions_dir.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ low level
    def _write(self, path: Path, data: bytes) -> None:
        """Write ``path`` atomically: temporary file, flush, fsync, rename."""
        tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
        try:
            with open(tmp, "wb") as f:
                f.write(data)
                f.flush()
                if self.fsync:
                    os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    def _sync_dir(self, path: Path) -> None:
        if self.fsync:
            _fsync_dir(path)

    def session_dir(self, sid: str) -> Path:
        return self.sessions_dir / sid

    @staticmethod
    def _role_name(role: str, version: int) -> str:
        return f"{role}.{version}.pt"

    def _role_payload(self, record: SessionRecord, role: str) -> Any:
        if role == "gaussians":
            return {k: v.detach().cpu().contiguous() for k, v in record.gmap.items()}
        if role == "information":
            return {k: v.detach().cpu().contiguous() for k, v in record.h_acc.items()}
        if role == "pool":
            return {
                "ids": torch.from_numpy(np.ascontiguousarray(record.pool_ids, dtype=np.int64)),
                "poses": torch.from_numpy(np.ascontiguousarray(record.pool_poses, np.float64)),
            }
        if role == "warm":
            return record.warm_state or {}
        raise ValueError(f"unknown role {role!r}")

    def _write_files(
        self, folder: Path, record: SessionRecord, roles: Iterable[str], blobs: dict[str, bytes]
    ) -> dict[str, str]:
        files = dict(record.files)
        for role in roles:
            name = self._role_name(role, record.version)
            buf = io.BytesIO()
            torch.save(self._role_payload(record, role), buf)
            self._write(folder / name, buf.getvalue())
            files[role] = name
        if blobs:
            (folder / VIEWS).mkdir(exist_ok=True)
            for name, data in blobs.items():
                self._write(folder / VIEWS / name, data)
            self._sync_dir(folder / VIEWS)
        return files

    def _write_manifest(self, folder: Path, record: SessionRecord) -> None:
        text = json.dumps(record.manifest(), separators=(",", ":"), allow_nan=False).encode()
        self._write(folder / MANIFEST, text)
        self._sync_dir(folder)

    # ------------------------------------------------------------------ API
    def create(self, record: SessionRecord, blobs: dict[str, bytes] | None = None) -> SessionRecord:
        """Persist a new session; FileExistsError if the id is taken on disk."""
        final = self.session_dir(record.id)
        if final.exists():
            raise FileExistsError(record.id)
        tmp = self.sessions_dir / f".creating-{record.id}-{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        try:
            files = self._write_files(tmp, record, ROLES, blobs or {})
            record = replace(record, files=files)
            self._write_manifest(tmp, record)
            os.rename(tmp, final)  # fails if a session of that id appeared meanwhile
            self._sync_dir(self.sessions_dir)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return record

    def save(
        self, record: SessionRecord, dirty: Iterable[str], blobs: dict[str, bytes] | None = None
    ) -> SessionRecord:
        """Persist a changed session: the ``dirty`` roles and new view ``blobs``, then the
        manifest. Returns ``record`` with its file names updated."""
        folder = self.session_dir(record.id)
        dirty = [r for r in ROLES if r in set(dirty)]
        files = self._write_files(folder, record, dirty, blobs or {})
        new = replace(record, files=files)
        self._write_manifest(folder, new)
        for role in dirty:
            old = record.files.get(role)
            if old and old != files[role]:
                (folder / old).unlink(missing_ok=True)
        return new

    def delete(self, sid: str) -> None:
        folder = self.session_dir(sid)
        if not folder.exists():
            return
        aside = self.sessions_dir / f".deleted-{sid}-{uuid.uuid4().hex[:8]}"
        os.rename(folder, aside)
        self._sync_dir(self.sessions_dir)
        shutil.rmtree(aside, ignore_errors=True)

    def delete_blobs(self, sid: str, names: Iterable[str]) -> None:
        for name in names:
            (self.session_dir(sid) / VIEWS / name).unlink(missing_ok=True)

    def read_blob(self, sid: str, name: str) -> bytes:
        return (self.session_dir(sid) / VIEWS / name).read_bytes()

    def blob_path(self, sid: str, name: str) -> Path:
        return self.session_dir(sid) / VIEWS / name

    def load_all(self) -> list[SessionRecord]:
        """Every persisted session; removes leftovers of interrupted writes."""
        out = []
        for entry in sorted(self.sessions_dir.iterdir()):
            if entry.name.startswith("."):
                if entry.name.startswith((".creating-", ".deleted-")):
                    shutil.rmtree(entry, ignore_errors=True)
                continue
            if not entry.is_dir():
                continue
            try:
                out.append(self._load(entry))
            except Exception as exc:  # a damaged session must not stop the others loading
                log.error("could not load session %s: %s", entry.name, exc)
        return out

    def _load(self, folder: Path) -> SessionRecord:
        with open(folder / MANIFEST, "rb") as f:
            m = json.load(f)
        if m.get("format") != FORMAT:
            raise StoreError(f"unknown manifest format {m.get('format')!r}")
        files: dict[str, str] = m["files"]

        def load(role: str) -> Any:
            return torch.load(folder / files[role], map_location="cpu", weights_only=True)

        g = load("gaussians")
        pool = load("pool")
        record = SessionRecord(
            id=m["id"],
            created_at=float(m["created_at"]),
            updated_at=float(m["updated_at"]),
            version=int(m["version"]),
            intrinsics=m["intrinsics"],
            bounds=m["bounds"],
            defaults=m["defaults"],
            information_config=m["information_config"],
            gmap=GaussianMap(**g),
            h_acc=dict(load("information")),
            pool_ids=pool["ids"].numpy().astype(np.int64),
            pool_poses=pool["poses"].numpy().astype(np.float64).reshape(-1, 4, 4),
            next_candidate_id=int(m["next_candidate_id"]),
            views=tuple(ViewRecord.from_json(v) for v in m["views"]),
            next_view_id=int(m["next_view_id"]),
            warm_state=self._load_warm(folder, files),
            files=files,
            mapper=m.get("mapper"),
        )
        self._collect_garbage(folder, record)
        return record

    @staticmethod
    def _load_warm(folder: Path, files: dict[str, str]) -> dict[str, Any] | None:
        # the warm-start state is a cache: losing it only costs the next selection a cold start
        try:
            state = torch.load(folder / files["warm"], map_location="cpu", weights_only=True)
        except Exception as exc:
            log.warning("ignoring the warm-start state of %s: %s", folder.name, exc)
            return None
        return state or None

    def _collect_garbage(self, folder: Path, record: SessionRecord) -> None:
        keep = set(record.files.values()) | {MANIFEST, VIEWS}
        for entry in folder.iterdir():
            if entry.name not in keep and entry.is_file():
                entry.unlink(missing_ok=True)
        views = folder / VIEWS
        if views.is_dir():
            names = {v.image_file for v in record.views} | {v.depth_file for v in record.views}
            for entry in views.iterdir():
                if entry.name not in names:
                    entry.unlink(missing_ok=True)

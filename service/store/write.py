"""The persistent session store: every acknowledged state change is on disk first, checked
when read back, and the version before it is kept.

Layout under ``<state_dir>/sessions/<session>/``::

    manifest.json            small JSON: settings, counters, views, the file names below and
                             their checksums; it checksums itself (agilegs.service.store.integrity)
    manifest.prev.json       the previous version's manifest (what a rollback restores)
    gaussians.<v>.pt         the Gaussians (torch.save of the five tensors)
    information.<v>.pt       Ĥ per parameter block
    pool.<v>.pt              candidate ids [D] and poses [D, 4, 4]
    warm.<v>.pt              the selector's warm-start state after the last commit
    views/<id>.rgb.<ext>     images as sent (png / jpg) or as .npy
    views/<id>.depth.npy     depth as sent

A change writes its new files under fresh names (``<v>`` is the session version that wrote
them; a file is never overwritten), each to a temporary file that is fsynced and renamed;
then the new manifest is written to a temporary file and fsynced, the current one becomes
``manifest.prev.json`` (a hard link), and the new one is renamed over ``manifest.json``,
which is the commit point; the folder is
fsynced; only then are the files that neither manifest names removed. A crash at any point
leaves the old manifest and its files, or the new ones; a write refused for lack of space
removes what it wrote and leaves the session as it was. :meth:`SessionStore.load_all` checks
every file against the manifest's checksums and reports a session whose files do not check
out as a :class:`~agilegs.service.store.integrity.Damage` (never skips it);
:meth:`SessionStore.repair` rolls such a session back to the previous version and drops
damaged frames. Sessions are created in a hidden folder renamed into place, and deleted by
renaming them aside before removing them.
"""

from __future__ import annotations

import errno
import io
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .integrity import (
    Damage,
    DamagedFile,
    ManifestError,
    checksum,
    decode_manifest,
    encode_manifest,
    load_each,
    read_checked,
)
from .read import inspect_folder
from .records import (
    MANIFEST,
    PREVIOUS,
    ROLE_FILE,
    ROLES,
    SESSION_NAME,
    VIEWS,
    SessionRecord,
    ViewRecord,
)

__all__ = ["MANIFEST", "PREVIOUS", "ROLES", "Repair", "SessionRecord", "SessionStore",
           "StoreError", "ViewRecord", "role_payload", "without_files"]

log = logging.getLogger(__name__)


class StoreError(RuntimeError):
    """The state folder could not be read or written."""


@dataclass(frozen=True)
class Repair:
    """What :meth:`SessionStore.repair` did: the record now persisted, the version it rolled
    back to (None: none), the views whose damaged frames it dropped."""

    record: SessionRecord
    rolled_back_to: int | None
    dropped_frames: tuple[int, ...]
    repaired: bool = True


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _disk_full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


class SessionStore:
    """Session records on disk under ``root/sessions`` (see the module docstring).

    Args:
        root: the state folder.
        fsync: fsync files and folders before a change is acknowledged.
    """

    def __init__(self, root: Path | str, *, fsync: bool = True) -> None:
        self.root = Path(root)
        self.sessions_dir = self.root / "sessions"
        self.fsync = fsync

    # ------------------------------------------------------------------ low level
    def _write(self, path: Path, data: bytes,
               before_rename: Callable[[], None] | None = None) -> str:
        """Write ``path`` atomically (temporary file, flush, fsync, ``before_rename()``,
        rename); its checksum."""
        tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
        try:
            with open(tmp, "wb") as f:
                f.write(data)
                f.flush()
                if self.fsync:
                    os.fsync(f.fileno())
            if before_rename is not None:
                before_rename()
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return checksum(data)

    def _sync_dir(self, path: Path) -> None:
        if self.fsync:
            _fsync_dir(path)

    def session_dir(self, sid: str) -> Path:
        return self.sessions_dir / sid

    @property
    def where(self) -> str:
        """The state folder, for logs and reports."""
        return str(self.root)

    @staticmethod
    def _role_name(role: str, version: int) -> str:
        return f"{role}.{version}.pt"

    def _role_payload(self, record: SessionRecord, role: str) -> Any:
        return role_payload(record, role)

    def _write_files(self, folder: Path, record: SessionRecord, roles: Iterable[str],
                     blobs: dict[str, bytes], written: list[Path]
                     ) -> tuple[dict[str, str], dict[str, str]]:
        """Write the ``roles`` of ``record`` and the view ``blobs``; their names and
        checksums merged into the record's (``written``: every path written, appended as it
        is, for the caller to remove on failure)."""
        files = dict(record.files)
        sums = dict(record.checksums)
        for role in roles:
            name = self._role_name(role, record.version)
            buf = io.BytesIO()
            torch.save(self._role_payload(record, role), buf)
            written.append(folder / name)
            sums[name] = self._write(folder / name, buf.getvalue())
            files[role] = name
        if blobs:
            (folder / VIEWS).mkdir(exist_ok=True)
            for name, data in blobs.items():
                written.append(folder / VIEWS / name)
                sums[f"{VIEWS}/{name}"] = self._write(folder / VIEWS / name, data)
            self._sync_dir(folder / VIEWS)
        named = replace(record, files=files).named_files()
        return files, {k: v for k, v in sums.items() if k in named}

    def _write_manifest(self, folder: Path, record: SessionRecord, *,
                        keep_previous: bool = False) -> None:
        """The commit point: ``record``'s manifest replaces the current one (which becomes
        the previous one when ``keep_previous``, once the new one is safely written)."""
        keep = (lambda: self._keep_previous(folder)) if keep_previous else None
        self._write(folder / MANIFEST, encode_manifest(record.manifest()), keep)
        self._sync_dir(folder)

    def _keep_previous(self, folder: Path) -> None:
        """The current manifest becomes ``manifest.prev.json`` (a hard link; a copy where the
        file system has none)."""
        cur = folder / MANIFEST
        tmp = folder / f".{PREVIOUS}.tmp-{uuid.uuid4().hex[:8]}"
        try:
            try:
                os.link(cur, tmp)
            except FileNotFoundError:
                return
            except OSError as exc:
                if _disk_full(exc):
                    raise
                shutil.copyfile(cur, tmp)
            os.replace(tmp, folder / PREVIOUS)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    # ------------------------------------------------------------------ API
    def create(self, record: SessionRecord, blobs: dict[str, bytes] | None = None) -> SessionRecord:
        """Persist a new session; FileExistsError if the id is taken on disk."""
        final = self.session_dir(record.id)
        if final.exists():
            raise FileExistsError(record.id)
        tmp = self.sessions_dir / f".creating-{record.id}-{uuid.uuid4().hex[:8]}"
        try:
            self.sessions_dir.mkdir(parents=True, exist_ok=True)
            tmp.mkdir()
            files, sums = self._write_files(tmp, record, ROLES, blobs or {}, [])
            record = replace(record, files=files, checksums=sums)
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
        manifest; the superseded version is kept as the previous one. Returns ``record``
        with its file names and checksums updated. On failure nothing it wrote is left and
        the session on disk is as it was."""
        folder = self.session_dir(record.id)
        dirty = [r for r in ROLES if r in set(dirty)]
        previous = set(record.files.values())  # the files of the version superseded
        written: list[Path] = []
        try:
            files, sums = self._write_files(folder, record, dirty, blobs or {}, written)
            new = replace(record, files=files, checksums=sums)
            self._write_manifest(folder, new, keep_previous=True)
        except BaseException:
            for path in written:
                path.unlink(missing_ok=True)
            raise
        self._collect(folder, set(files.values()) | previous)
        return new

    def delete(self, sid: str) -> None:
        folder = self.session_dir(sid)
        if not folder.exists():
            return
        aside = self.sessions_dir / f".deleted-{sid}-{uuid.uuid4().hex[:8]}"
        os.rename(folder, aside)
        self._sync_dir(self.sessions_dir)
        shutil.rmtree(aside, ignore_errors=True)

    def read_blob(self, sid: str, name: str, expected: str | None = None) -> bytes:
        """The bytes of ``views/<name>``; :class:`DamagedFile` unless they match the
        ``expected`` checksum (the record's)."""
        data, problem = read_checked(self.blob_path(sid, name), f"{VIEWS}/{name}", expected)
        if problem is not None:
            raise DamagedFile(problem)
        assert data is not None
        return data

    def blob_path(self, sid: str, name: str) -> Path:
        return self.session_dir(sid) / VIEWS / name

    def session_ids(self, *, tidy: bool = True) -> list[str]:
        """The sessions on disk (folder names), sorted; folders that cannot be session ids
        are skipped, and (``tidy``) leftovers of interrupted creates and deletes removed."""
        out: list[str] = []
        if not self.sessions_dir.is_dir():
            return out
        for entry in sorted(self.sessions_dir.iterdir()):
            if entry.name.startswith("."):
                if tidy and entry.name.startswith((".creating-", ".deleted-")):
                    shutil.rmtree(entry, ignore_errors=True)
                continue
            if not entry.is_dir():
                continue
            if not SESSION_NAME.match(entry.name):
                log.warning("ignoring %s: not a session folder", entry)
                continue
            out.append(entry.name)
        return out

    def load_all(self) -> tuple[list[SessionRecord], list[Damage]]:
        """Every persisted session, checked: the intact ones, and the damaged ones with what
        is wrong (none is skipped). Removes leftovers of interrupted writes."""
        return load_each(self.session_ids(), self.inspect, lambda sid, rec: self._collect(
            self.session_dir(sid), self._referenced(sid, rec),
            views=self._referenced_views(sid, rec)))

    # ------------------------------------------------------------------ checking
    def forget(self, sid: str) -> None:
        """Nothing to forget: the folder has one server, which holds every session in it."""

    def inspect(self, sid: str) -> SessionRecord | Damage:
        """Session ``sid`` read back and checked (see
        :func:`~agilegs.service.store.read.inspect_folder`)."""
        return inspect_folder(self.session_dir(sid))

    # ------------------------------------------------------------------ repair
    def repair(self, sid: str) -> Repair:
        """Bring damaged session ``sid`` back: roll it back to the previous version when the
        current one's manifest or role files do not check out, and drop the damaged images
        / depth of its views. The result is a new version (numbered past every version the
        folder has seen). ``repaired`` is False when nothing was damaged; StoreError when
        nothing intact is left."""
        got = self.inspect(sid)
        if not isinstance(got, Damage):
            return Repair(got, None, (), repaired=False)
        target = got.record
        if not isinstance(target, SessionRecord):
            raise StoreError(f"session {sid!r}: {got.plan()}")
        folder = self.session_dir(sid)
        bad = set(got.frame_files)
        views = tuple(without_files(v, bad) for v in target.views)
        seen = [target.version, got.version or 0, *self._file_versions(folder)]
        new = replace(target, version=max(seen) + 1, updated_at=time.time(), views=views)
        written: list[Path] = []
        try:
            files, sums = self._write_files(folder, new, ("warm",), {}, written)
            new = replace(new, files=files, checksums=sums)
            self._write_manifest(folder, new)  # the previous manifest stays what it was
        except BaseException:
            for path in written:
                path.unlink(missing_ok=True)
            raise
        self._collect(folder, self._referenced(sid, new), views=self._referenced_views(sid, new))
        log.warning("session %s repaired: %s; now version %d", sid, got.plan(), new.version)
        return Repair(new, got.rollback_to, got.drop_frames)

    # ------------------------------------------------------------------ garbage
    def _previous_manifest(self, sid: str) -> dict[str, Any] | None:
        try:
            return decode_manifest((self.session_dir(sid) / PREVIOUS).read_bytes())
        except (OSError, ManifestError):
            return None

    def _referenced(self, sid: str, record: SessionRecord) -> set[str]:
        """The role files of ``record`` and of the previous manifest."""
        keep = set(record.files.values())
        prev = self._previous_manifest(sid)
        if prev is not None:
            keep |= set(dict(prev.get("files") or {}).values())
        return keep

    def _referenced_views(self, sid: str, record: SessionRecord) -> set[str]:
        """The view files of ``record`` and of the previous manifest."""
        keep = {n for n in record.named_files() if n.startswith(VIEWS + "/")}
        prev = self._previous_manifest(sid)
        if prev is not None:
            for v in prev.get("views") or []:
                keep.update(f"{VIEWS}/{n}" for n in (v.get("image_file"), v.get("depth_file"))
                            if n)
        return keep

    @staticmethod
    def _file_versions(folder: Path) -> list[int]:
        out = []
        for entry in folder.iterdir():
            hit = ROLE_FILE.match(entry.name)
            if hit:
                out.append(int(hit.group(2)))
        return out

    def _collect(self, folder: Path, keep: set[str], *, views: set[str] | None = None) -> None:
        """Remove role files not in ``keep``, leftover temporary files, and (``views`` given)
        view files not in ``views``."""
        for entry in folder.iterdir():
            name = entry.name
            if (ROLE_FILE.match(name) and name not in keep) or ".tmp-" in name:
                if entry.is_file():
                    entry.unlink(missing_ok=True)
        vdir = folder / VIEWS
        if views is not None and vdir.is_dir():
            for entry in vdir.iterdir():
                if f"{VIEWS}/{entry.name}" not in views and entry.is_file():
                    entry.unlink(missing_ok=True)


def role_payload(record: SessionRecord, role: str) -> Any:
    """What the file of ``role`` holds for ``record`` (what ``torch.save`` writes)."""
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


def without_files(view: ViewRecord, bad: set[str]) -> ViewRecord:
    """``view`` without its files in ``bad`` (``views/<name>``)."""
    changes: dict[str, Any] = {}
    if view.image_file and f"{VIEWS}/{view.image_file}" in bad:
        changes.update(image_file=None, image_encoding=None)
    if view.depth_file and f"{VIEWS}/{view.depth_file}" in bad:
        changes.update(depth_file=None, depth_scale=1.0)
    if not changes:
        return view
    out = replace(view, **changes)
    if out.image_file is None and out.depth_file is None:
        out = replace(out, intrinsics=None)
    return out

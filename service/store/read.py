"""Reading a session back and checking it: every file against the checksums of its
manifest, every tensor file against the shapes it must have (see
:mod:`agilegs.service.store.integrity`).

:func:`inspect_session` gives the session's record when everything checks out, else a
:class:`~agilegs.service.store.integrity.Damage`: which files, what is wrong, and the state a
repair starts from (the current version when only frames are damaged, else the previous
version, ``manifest.prev.json``, when that one checks out). It reads through a
:class:`Source`: a session folder (:func:`inspect_folder`) or a session's objects in an object
store (:mod:`agilegs.service.store.objects`); both give the same answers.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from ..nbv import GaussianMap
from .integrity import Damage, FileProblem, ManifestError, checksum, decode_manifest, read_checked
from .records import (
    MANIFEST,
    PREVIOUS,
    REQUIRED,
    VIEWS,
    AppliedRequest,
    SessionRecord,
    ViewRecord,
    view_id,
)

__all__ = ["FolderSource", "Source", "Version", "inspect_folder", "inspect_session",
           "read_version"]

log = logging.getLogger(__name__)


@dataclass
class Version:
    """One manifest of a session folder, read and checked."""

    manifest: dict[str, Any] | None = None  # None: the manifest itself does not check out
    record: SessionRecord | None = None  # None: the manifest or a role file does not check out
    problems: list[FileProblem] = field(default_factory=list)

    @property
    def frame_problems(self) -> list[FileProblem]:
        return [p for p in self.problems if p.file.startswith(VIEWS + "/")]


class Source(Protocol):
    """Where a session's files are read from: ``session`` is its id, ``read(rel)`` the bytes
    of the file ``rel`` (``manifest.json``, ``gaussians.3.pt``, ``views/<name>``;
    FileNotFoundError when it is missing, OSError when it cannot be read)."""

    @property
    def session(self) -> str: ...

    def read(self, rel: str) -> bytes: ...


class FolderSource:
    """A session folder as a :class:`Source`."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder

    @property
    def session(self) -> str:
        return self.folder.name

    def read(self, rel: str) -> bytes:
        return (self.folder / rel).read_bytes()


def inspect_folder(folder: Path) -> SessionRecord | Damage:
    """The session in ``folder``, read back and checked (:func:`inspect_session`)."""
    return inspect_session(FolderSource(folder))


def inspect_session(source: Source) -> SessionRecord | Damage:
    """The session of ``source``, read back and checked: its record when every file checks
    out (a damaged warm-start state is dropped: a cold start), else what is damaged and what
    a repair would restore."""
    cur = read_version(source, MANIFEST)
    if not cur.problems:
        assert cur.record is not None
        return cur.record
    version = int(cur.manifest["version"]) if cur.manifest is not None else None
    target, rollback, frames = cur.record, None, cur.frame_problems
    if target is None:
        prev = read_version(source, PREVIOUS)
        if prev.record is not None:
            target, rollback, frames = prev.record, prev.record.version, prev.frame_problems
        else:
            frames = []
    drop = sorted({i for i in (view_id(p.file) for p in frames) if i is not None})
    return Damage(source.session, tuple(cur.problems), version=version, rollback_to=rollback,
                  drop_frames=tuple(drop), frame_files=tuple(p.file for p in frames),
                  record=target, manifest=cur.manifest)


def read_version(source: Source | Path, name: str) -> Version:
    """The manifest ``name`` of ``source`` (a session folder, or any :class:`Source`) and
    every file it names, checked."""
    src: Source = FolderSource(source) if isinstance(source, Path) else source
    data, problem = read_checked(partial(src.read, name), name, None)
    if problem is not None or data is None:
        return Version(problems=[problem or FileProblem(name, "unreadable")])
    try:
        m = decode_manifest(data)
        if m.get("id") != src.session:
            raise ManifestError(f"names session {m.get('id')!r}, not {src.session!r}")
        files: dict[str, str] = dict(m["files"])
        views = tuple(ViewRecord.from_json(v) for v in m["views"])
        version = int(m["version"])
        for r in m.get("requests") or ():
            AppliedRequest.from_json(r)
    except ManifestError as exc:
        return Version(problems=[FileProblem(name, exc.problem)])
    except (KeyError, TypeError, ValueError) as exc:
        return Version(problems=[FileProblem(name, f"unreadable ({type(exc).__name__}: {exc})")])
    legacy = m.get("format") == 1  # no checksums: the files as read become the reference
    sums: dict[str, str] = dict(m.get("checksums") or {})
    out = Version(manifest=m)
    payloads: dict[str, Any] = {}
    for role in (*REQUIRED, "warm"):
        fname = files.get(role)
        if fname is None:
            if role != "warm":
                out.problems.append(FileProblem(name, f"names no {role} file"))
            continue
        raw, problem = read_checked(partial(src.read, fname), fname, sums.get(fname))
        if raw is not None:
            try:
                obj = torch.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
                payloads[role] = check_payload(role, obj, payloads)
                if legacy:
                    sums[fname] = checksum(raw)
            except Exception as exc:
                problem = FileProblem(fname, f"unreadable ({type(exc).__name__}: {exc})")
        if problem is None:
            continue
        if role == "warm":
            log.warning("ignoring the warm-start state of %s: %s", src.session, problem)
        else:
            out.problems.append(problem)
    for v in views:
        for fname in (v.image_file, v.depth_file):
            if fname:
                rel = f"{VIEWS}/{fname}"
                raw, problem = read_checked(partial(src.read, rel), rel, sums.get(rel))
                if problem is not None:
                    out.problems.append(problem)
                elif legacy and raw is not None:
                    sums[rel] = checksum(raw)
    if any(not p.file.startswith(VIEWS + "/") for p in out.problems):
        return out
    try:
        out.record = _record(m, version, views, files, payloads, sums)
    except (KeyError, TypeError, ValueError) as exc:
        out.problems.append(FileProblem(name, f"unreadable ({type(exc).__name__}: {exc})"))
    return out


def _record(m: dict[str, Any], version: int, views: tuple[ViewRecord, ...],
            files: dict[str, str], payloads: dict[str, Any], sums: dict[str, str]
            ) -> SessionRecord:
    pool = payloads["pool"]
    return SessionRecord(
        id=m["id"],
        created_at=float(m["created_at"]),
        updated_at=float(m["updated_at"]),
        version=version,
        intrinsics=m["intrinsics"],
        bounds=m["bounds"],
        defaults=m["defaults"],
        information_config=m["information_config"],
        gmap=payloads["gaussians"],
        h_acc=payloads["information"],
        pool_ids=pool["ids"].numpy().astype(np.int64),
        pool_poses=pool["poses"].numpy().astype(np.float64).reshape(-1, 4, 4),
        next_candidate_id=int(m["next_candidate_id"]),
        views=views,
        next_view_id=int(m["next_view_id"]),
        warm_state=payloads.get("warm") or None,
        files=files,
        mapper=m.get("mapper"),
        checksums=sums,
        requests=tuple(AppliedRequest.from_json(r) for r in m.get("requests") or ()),
    )


def check_payload(role: str, payload: Any, loaded: dict[str, Any]) -> Any:
    """A role file's payload as the record holds it; ValueError if its content does not fit
    (its own shapes, or the Gaussians loaded before it)."""
    if role == "gaussians":
        return GaussianMap(**payload)
    if role == "information":
        h = dict(payload)
        g = loaded.get("gaussians")
        if g is not None:
            want = {k: tuple(v.shape) for k, v in g.items()}
            got = {k: tuple(v.shape) for k, v in h.items()}
            if want != got:
                raise ValueError(f"its blocks {got} do not fit the Gaussians {want}")
        return h
    if role == "pool":
        ids, poses = payload["ids"], payload["poses"]
        if ids.ndim != 1 or tuple(poses.shape) != (ids.shape[0], 4, 4):
            raise ValueError(f"ids {list(ids.shape)} and poses {list(poses.shape)} do not fit")
        return payload
    return payload

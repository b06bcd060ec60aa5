"""Checksums of a session's state files, the manifest's own checksum, and what a failed check
reports.

Every file the store writes gets a checksum, ``"<size>:<sha256 hex>"``, kept in the manifest
(``checksums``: path under the session folder -> checksum). The manifest checksums itself:
``checksum`` is ``sha256:<hex>`` over the canonical JSON (sorted keys, no spaces) of every
other field, so a truncated manifest, a flipped byte or a field changed by hand is caught
before anything in it is believed. Manifests of format 1 (written before checksums existed)
still load, unchecked.

A file that does not check out is a :class:`FileProblem` (which file, what is wrong); a
session with any is a :class:`Damage`, which also says what a repair would restore
(:meth:`agilegs.service.store.write.SessionStore.repair`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "is_tombstone",
    "lease_of",
    "FORMAT",
    "Damage",
    "DamagedFile",
    "FileProblem",
    "ManifestError",
    "check",
    "checksum",
    "decode_manifest",
    "encode_manifest",
    "load_each",
    "read_checked",
]

log = logging.getLogger(__name__)

FORMAT = 2
"""The manifest format written (1: no checksums; still read)."""


@dataclass(frozen=True)
class FileProblem:
    """One file that does not check out: its path under the session folder, what is wrong."""

    file: str
    problem: str

    def __str__(self) -> str:
        return f"{self.file}: {self.problem}"


class DamagedFile(RuntimeError):
    """A state file read back does not check out."""

    def __init__(self, problem: FileProblem) -> None:
        super().__init__(str(problem))
        self.problem = problem


class ManifestError(ValueError):
    """A manifest that cannot be believed (``problem`` says why)."""

    def __init__(self, problem: str) -> None:
        super().__init__(problem)
        self.problem = problem


def checksum(data: bytes) -> str:
    """``"<size>:<sha256 hex>"`` of ``data``."""
    return f"{len(data)}:{hashlib.sha256(data).hexdigest()}"


def check(data: bytes, expected: str | None) -> str | None:
    """What is wrong with ``data`` against its ``expected`` checksum (None: nothing, or no
    checksum to check against)."""
    if expected is None:
        return None
    size_text, _, digest = expected.partition(":")
    try:
        size = int(size_text)
    except ValueError:
        return f"its recorded checksum {expected!r} is malformed"
    if len(data) < size:
        return f"truncated ({len(data)} of {size} bytes)"
    if len(data) > size:
        return f"{len(data) - size} bytes longer than written ({size} bytes)"
    if hashlib.sha256(data).hexdigest() != digest:
        return "checksum mismatch (its bytes changed since they were written)"
    return None


def read_checked(path: Path | Callable[[], bytes], rel: str, expected: str | None
                 ) -> tuple[bytes | None, FileProblem | None]:
    """The bytes of ``path`` (a file, or a function reading them: an object in an object
    store) if they check out against ``expected``; else the problem (``rel``: the file's name
    in reports). A reader raises FileNotFoundError for a missing file, OSError when it cannot
    read it."""
    try:
        data = path.read_bytes() if isinstance(path, Path) else path()
    except FileNotFoundError:
        return None, FileProblem(rel, "missing")
    except OSError as exc:
        return None, FileProblem(rel, f"unreadable ({exc.strerror or exc})")
    problem = check(data, expected)
    if problem is not None:
        return None, FileProblem(rel, problem)
    return data, None


def _canonical(body: dict[str, Any]) -> bytes:
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def encode_manifest(body: dict[str, Any]) -> bytes:
    """The manifest file's bytes: ``body`` (format :data:`FORMAT`) with its checksum."""
    digest = hashlib.sha256(_canonical(body)).hexdigest()
    return json.dumps({**body, "checksum": f"sha256:{digest}"}, separators=(",", ":"),
                      allow_nan=False).encode()


def decode_manifest(data: bytes) -> dict[str, Any]:
    """The manifest in ``data``, its checksum checked (format 1: unchecked); ManifestError
    saying what is wrong otherwise."""
    if not data:
        raise ManifestError("empty")
    try:
        m = json.loads(data)
    except ValueError:  # includes bytes that are not UTF-8
        raise ManifestError(f"not valid JSON ({len(data)} bytes: truncated or overwritten)"
                            ) from None
    if not isinstance(m, dict):
        raise ManifestError("not a JSON object")
    fmt = m.get("format")
    if fmt == 1:
        return m
    if fmt != FORMAT:
        raise ManifestError(f"unknown format {fmt!r}")
    given = m.pop("checksum", None)
    if not isinstance(given, str):
        raise ManifestError("no checksum")
    if given != f"sha256:{hashlib.sha256(_canonical(m)).hexdigest()}":
        raise ManifestError("checksum mismatch (its bytes changed since they were written)")
    return m


@dataclass(frozen=True)
class Damage:
    """A persisted session whose files do not check out, and what a repair would restore.

    Attributes:
        session: the session id (its folder's name).
        files: every file of the current version that does not check out.
        version: the damaged version (None: its manifest is unreadable).
        rollback_to: the intact earlier version a repair restores (None: no rollback; the
            current version is kept, or nothing intact is left).
        drop_frames: views whose damaged image / depth a repair drops.
        frame_files: those damaged files (``views/<name>``) of the state a repair starts from.
        record: the state a repair starts from (a ``SessionRecord``: the current version's
            when only frames are damaged, else the earlier version's), None when nothing
            intact is left.
        manifest: the damaged version's manifest when it checks out (numbers for listings).
        detected_at: unix time of the check.
    """

    session: str
    files: tuple[FileProblem, ...]
    version: int | None = None
    rollback_to: int | None = None
    drop_frames: tuple[int, ...] = ()
    frame_files: tuple[str, ...] = ()
    record: Any = None
    manifest: dict[str, Any] | None = None
    detected_at: float = field(default_factory=time.time)

    @property
    def repairable(self) -> bool:
        return self.record is not None

    def reason(self) -> str:
        """Which files, what is wrong: ``manifest.json: empty; views/v00000002.rgb.png: ...``."""
        return "; ".join(str(p) for p in self.files)

    def plan(self) -> str:
        """What a repair would do, in words."""
        if self.record is None:
            return ("nothing intact is left to restore: delete the session, or restore its "
                    "folder from a backup")
        steps = []
        if self.rollback_to is not None:
            lost = f"version {self.version}" if self.version is not None else "later versions"
            steps.append(f"roll back to version {self.rollback_to} (what {lost} changed is "
                         "lost)")
        if self.drop_frames:
            ids = ", ".join(str(i) for i in self.drop_frames)
            steps.append(f"drop the damaged images / depth of views {ids} (the views, their "
                         "poses and Ĥ stay)")
        return "; then ".join(steps) or "rewrite the manifest"


def lease_of(manifest: bytes | None) -> dict[str, Any] | None:
    """The lease a manifest's bytes record (None: none, or they do not decode)."""
    if manifest is None:
        return None
    try:
        lease = decode_manifest(manifest).get("lease")
    except ManifestError:
        return None
    return lease if isinstance(lease, dict) else None


def is_tombstone(manifest: bytes | None) -> bool:
    """Whether a manifest's bytes are a deletion's tombstone (the session is gone)."""
    if manifest is None:
        return False
    try:
        return decode_manifest(manifest).get("deleted") is True
    except ManifestError:
        return False


def load_each(ids: Iterable[str], check: Callable[[str], Any],
              on_intact: Callable[[str, Any], None]) -> tuple[list[Any], list[Damage]]:
    """Every session of ``ids`` checked by ``check(sid)`` (a record, a :class:`Damage`, or None
    to leave it out), sorted into the intact records and the damaged ones; ``on_intact(sid,
    record)`` after each intact one. A check that raises makes its session damaged (its
    manifest unreadable), never stops the others loading."""
    records: list[Any] = []
    damaged: list[Damage] = []
    for sid in ids:
        try:
            got = check(sid)
        except Exception as exc:
            log.exception("could not check session %s", sid)
            got = Damage(sid, (FileProblem("manifest.json", f"unreadable ({exc})"),))
        if got is None:
            continue
        if isinstance(got, Damage):
            log.error("session %s is damaged: %s (repair: %s)", sid, got.reason(), got.plan())
            damaged.append(got)
        else:
            records.append(got)
            on_intact(sid, got)
    return records, damaged

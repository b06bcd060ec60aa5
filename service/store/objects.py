"""The session store in an object store (any S3 API): what ``agilegs serve --state-url
s3://bucket/prefix`` keeps its sessions in, so that several instances share them.

Layout under the prefix::

    sessions/<session>/manifest.json       the current version (the commit point)
    sessions/<session>/manifest.prev.json  the previous version's manifest
    sessions/<session>/gaussians.<v>.<t>.pt  information.<v>.<t>.pt  pool.<v>.<t>.pt
                                           warm.<v>.<t>.pt
    sessions/<session>/views/v<id>.<t>.rgb.<png|jpg|npy>  views/v<id>.<t>.depth.npy

The manifest and the checksums are those of the state folder
(:mod:`agilegs.service.store.write`, :mod:`agilegs.service.store.integrity`); reading back
and checking go through the same code (:func:`~agilegs.service.store.read.inspect_session`),
so a damaged object is reported, and repaired, exactly as a damaged file is. What differs is
how a version is committed:

- Every file of a version is a new object under a fresh key (``<t>``: a random token per
  write): an object, once written, is never written again, and two writers never write the
  same key.
- The manifest is the commit point, written by a conditional put: ``If-None-Match: *`` when a
  session is created (of two instances creating one id at once, exactly one wins; the other
  gets :class:`FileExistsError`, which the service answers 409), ``If-Match: <ETag>`` of the
  manifest as this instance last read or wrote it for every later change. A commit whose
  ETag is no longer current (another instance took the session over and committed) fails
  with :class:`Fenced`, and this instance's new objects are removed: a stale owner writes
  nothing anyone reads.
- Before the commit, the current manifest's bytes (as this instance holds them, checked
  against the store's ETag first) become ``manifest.prev.json``, the version a rollback
  restores.
- After the commit, the objects of the version before the previous one that neither kept
  version names are removed: only keys this instance knows, never by listing, so a stale
  owner cannot remove a newer owner's objects. Leftovers of interrupted writes (objects no
  manifest names) are removed when the sessions are loaded, once they are older than
  :data:`LEFTOVER_AGE` (a write in flight elsewhere is younger).
- A session is deleted by removing its manifest (then the rest).

The ETag an instance commits against is learnt when it takes a session over
(:meth:`take_over`, :meth:`load_all`) and after each of its commits; :meth:`inspect` reads
without learning, so a stale owner checking a session's files does not become current by it.

Ownership: the manifest written to the object store records a lease, ``{"owner": <instance>,
"epoch": n, "since": <unix time>}`` (a field a state folder's manifest does not have; the read
path ignores it). Taking a session over rewrites its manifest with epoch + 1 by a conditional
put: that write is the handover, and it fences the previous owner, whose next commit's
``If-Match`` fails.
"""

from __future__ import annotations

import io
import logging
import re
import threading
import time
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

import torch

from .blobs import Blobs, PreconditionFailed, open_blobs
from .integrity import (
    FORMAT,
    Damage,
    DamagedFile,
    checksum,
    decode_manifest,
    encode_manifest,
    is_tombstone,
    lease_of,
    load_each,
    read_checked,
)
from .read import inspect_session
from .records import (
    MANIFEST,
    PREVIOUS,
    ROLES,
    SESSION_NAME,
    VIEWS,
    SessionRecord,
    ViewRecord,
    named_in,
)
from .write import Repair, SessionStore, StoreError, role_payload, without_files

__all__ = ["LEFTOVER_AGE", "AnyStore", "Fenced", "ObjectSessionStore", "folder_of", "open_store"]

log = logging.getLogger(__name__)

LEFTOVER_AGE = 900.0
"""Seconds after which an object that no manifest names is a leftover (removed on loading)."""

SESSIONS = "sessions/"
_ROLE_OBJECT = re.compile(r"^(gaussians|information|pool|warm)\.(\d+)\.")


class Fenced(StoreError):
    """A commit refused because the session's manifest changed since this instance last read
    or wrote it: another instance owns the session now."""


@dataclass
class _Head:
    """What this instance knows of a session's committed state."""

    etag: str | None  # of manifest.json as last read or written here (None: absent)
    manifest: bytes | None  # its bytes
    named: set[str] = field(default_factory=set)  # what the current version names
    previous: set[str] = field(default_factory=set)  # what the previous version names
    lease: dict[str, Any] | None = None  # {"owner", "epoch", "since"} this instance holds


class _Source:
    """A session's objects as a :class:`~agilegs.service.store.read.Source`; remembers the
    manifest it read (bytes and ETag)."""

    def __init__(self, blobs: Blobs, sid: str) -> None:
        self.blobs = blobs
        self.sid = sid
        self.manifest: tuple[bytes, str | None] | None = None
        self.manifest_seen = False

    @property
    def session(self) -> str:
        return self.sid

    def read(self, rel: str) -> bytes:
        try:
            data, etag = self.blobs.get(_key(self.sid, rel))
        except FileNotFoundError:
            if rel == MANIFEST:
                self.manifest_seen = True
            raise
        if rel == MANIFEST and is_tombstone(data):
            self.manifest_seen = True
            raise FileNotFoundError(rel)  # deleted: its objects are being removed
        if rel == MANIFEST and self.manifest is None:
            self.manifest = (data, etag)
            self.manifest_seen = True
        return data


def _key(sid: str, rel: str) -> str:
    return f"{SESSIONS}{sid}/{rel}"


def _token() -> str:
    return uuid.uuid4().hex[:10]


class ObjectSessionStore:
    """Session records in an object store (see the module docstring); the same operations as
    :class:`~agilegs.service.store.write.SessionStore`.

    Args:
        blobs: the object store (:func:`~agilegs.service.store.blobs.open_blobs`).
        owner: this instance's id, recorded in the leases it takes.
    """

    def __init__(self, blobs: Blobs, owner: str | None = None) -> None:
        self.blobs = blobs
        self.owner = owner
        self._heads: dict[str, _Head] = {}
        self._lock = threading.Lock()

    def _encode(self, record: SessionRecord, lease: dict[str, Any] | None) -> bytes:
        body = record.manifest()
        if lease is not None:
            body["lease"] = lease
        return encode_manifest(body)

    def _new_lease(self, epoch: int) -> dict[str, Any]:
        return {"owner": self.owner, "epoch": epoch, "since": time.time()}

    @property
    def where(self) -> str:
        return self.blobs.where

    # ------------------------------------------------------------------ writing
    def _write_files(self, record: SessionRecord, roles: Iterable[str], blobs: dict[str, bytes],
                     written: list[str]) -> SessionRecord:
        """Write the ``roles`` of ``record`` and the view ``blobs`` as new objects; ``record``
        naming them, with their checksums (``written``: every key written, for the caller to
        remove on failure)."""
        token = _token()
        files = dict(record.files)
        sums = dict(record.checksums)
        for role in roles:
            name = f"{role}.{record.version}.{token}.pt"
            buf = io.BytesIO()
            torch.save(role_payload(record, role), buf)
            data = buf.getvalue()
            written.append(_key(record.id, name))
            self.blobs.put_if_absent(_key(record.id, name), data)
            sums[name] = checksum(data)
            files[role] = name
        renamed: dict[str, str] = {}
        for name, data in blobs.items():
            head, _, tail = name.partition(".")
            fresh = f"{head}.{token}.{tail}"
            rel = f"{VIEWS}/{fresh}"
            written.append(_key(record.id, rel))
            self.blobs.put_if_absent(_key(record.id, rel), data)
            sums[rel] = checksum(data)
            renamed[name] = fresh
        views = record.views
        if renamed:
            views = tuple(_renamed(v, renamed) for v in record.views)
        new = replace(record, files=files, views=views)
        named = new.named_files()
        return replace(new, checksums={k: v for k, v in sums.items() if k in named})

    def _remove(self, keys: Iterable[str]) -> None:
        try:
            self.blobs.delete(keys)
        except OSError as exc:
            log.warning("could not remove objects: %s", exc)

    def create(self, record: SessionRecord, blobs: dict[str, bytes] | None = None
               ) -> SessionRecord:
        """Persist a new session; FileExistsError if the id is taken in the store (the
        conditional create of its manifest lost)."""
        written: list[str] = []
        try:
            new = self._write_files(record, ROLES, blobs or {}, written)
            lease = self._new_lease(1)
            data = self._encode(new, lease)
            etag = self._put_new(record.id, data)
        except PreconditionFailed:
            self._remove(written)
            raise FileExistsError(record.id) from None
        except BaseException:
            self._remove(written)
            raise
        with self._lock:
            self._heads[record.id] = _Head(etag, data, new.named_files(), set(), lease)
        return new

    def _put_new(self, sid: str, data: bytes) -> str | None:
        """Create the manifest of ``sid`` if none is there (or a deletion's tombstone, left
        by a deleter that died: replaced conditionally); PreconditionFailed otherwise."""
        key = _key(sid, MANIFEST)
        try:
            return self.blobs.put_if_absent(key, data)
        except PreconditionFailed:
            try:
                there, etag = self.blobs.get(key)
            except FileNotFoundError:
                raise PreconditionFailed(key) from None
            if not is_tombstone(there) or etag is None:
                raise
            return self.blobs.put_if_match(key, data, etag)

    def save(self, record: SessionRecord, dirty: Iterable[str],
             blobs: dict[str, bytes] | None = None) -> SessionRecord:
        """Persist a changed session: the ``dirty`` roles and new view ``blobs`` as new
        objects, then the manifest by a conditional put (:class:`Fenced` if another instance
        committed since). On failure the objects it wrote are removed and the session in
        the store is as it was."""
        sid = record.id
        head = self._head(sid)
        dirty = [r for r in ROLES if r in set(dirty)]
        new, etag, data = self._write_version(sid, head, record, dirty, blobs or {}, head.lease,
                                              keep_previous=True)
        named = new.named_files()
        with self._lock:
            self._heads[sid] = _Head(etag, data, named, head.named, head.lease)
        self._remove(_key(sid, n) for n in head.previous - named - head.named)
        return new

    def _write_version(self, sid: str, head: _Head, record: SessionRecord,
                       roles: Iterable[str], blobs: dict[str, bytes],
                       lease: dict[str, Any] | None, *, keep_previous: bool
                       ) -> tuple[SessionRecord, str | None, bytes]:
        """Write ``record``'s ``roles`` and ``blobs`` as new objects and commit its manifest
        (with ``lease``) over ``head`` (:meth:`_commit`): the record with its file names, the
        manifest's ETag and bytes. On failure the objects written are removed."""
        written: list[str] = []
        try:
            new = self._write_files(record, roles, blobs, written)
            data = self._encode(new, lease)
            return new, self._commit(sid, head, data, keep_previous=keep_previous), data
        except BaseException:
            self._remove(written)
            raise

    def _head(self, sid: str) -> _Head:
        with self._lock:
            head = self._heads.get(sid)
        if head is None:
            raise Fenced(f"session {sid!r} is not held here (take it over first)")
        return head

    def _commit(self, sid: str, head: _Head, data: bytes, *, keep_previous: bool) -> str | None:
        """Write ``data`` as the manifest if it is still the one ``head`` knows (the current
        one first becoming the previous one when ``keep_previous``); its new ETag."""
        key = _key(sid, MANIFEST)
        if keep_previous and head.manifest is not None:
            try:
                _, now = self.blobs.get(key)
            except FileNotFoundError:
                now = None
            if now != head.etag:
                raise Fenced(f"session {sid!r} was changed by another instance")
            self.blobs.put(_key(sid, PREVIOUS), head.manifest)
        try:
            if head.etag is None:
                return self.blobs.put_if_absent(key, data)
            return self.blobs.put_if_match(key, data, head.etag)
        except PreconditionFailed:
            raise Fenced(f"session {sid!r} was changed by another instance") from None

    def delete(self, sid: str) -> None:
        """Remove the session: a tombstone first, put conditionally on the manifest this
        instance last committed (:class:`Fenced` when another instance took the session
        over: a stale owner deletes nothing), so that the session is gone from then on;
        then its objects, the tombstone last. A session this instance does not hold (a
        damaged one, ``agilegs store``) loses its manifest unconditionally."""
        key = _key(sid, MANIFEST)
        with self._lock:
            head = self._heads.get(sid)
        if head is not None and head.etag is not None:
            tomb = encode_manifest({"format": FORMAT, "id": sid, "deleted": True,
                                    "lease": head.lease})
            try:
                self.blobs.put_if_match(key, tomb, head.etag)
            except PreconditionFailed:
                raise Fenced(f"session {sid!r} was changed by another instance") from None
            except FileNotFoundError:
                pass
        self.blobs.delete(b.key for b in self.blobs.list(f"{SESSIONS}{sid}/")
                          if b.key != key)
        self.blobs.delete([key])
        with self._lock:
            self._heads.pop(sid, None)

    def forget(self, sid: str) -> None:
        """Stop tracking session ``sid`` (its lease is lost: this instance writes it no
        more)."""
        with self._lock:
            self._heads.pop(sid, None)

    def read_blob(self, sid: str, name: str, expected: str | None = None) -> bytes:
        """The bytes of ``views/<name>``; :class:`DamagedFile` unless they match the
        ``expected`` checksum (the record's)."""
        rel = f"{VIEWS}/{name}"
        data, problem = read_checked(lambda: self.blobs.get(_key(sid, rel))[0], rel, expected)
        if problem is not None:
            raise DamagedFile(problem)
        assert data is not None
        return data

    # ------------------------------------------------------------------ reading
    def session_ids(self, *, tidy: bool = True) -> list[str]:
        """The sessions in the store (their key prefixes), sorted; names that cannot be
        session ids are skipped."""
        out: list[str] = []
        for name in self.blobs.children(SESSIONS):
            if SESSION_NAME.match(name):
                out.append(name)
            else:
                log.warning("ignoring %s%s: not a session", SESSIONS, name)
        return out

    def inspect(self, sid: str) -> SessionRecord | Damage:
        """Session ``sid`` read back and checked (learns nothing: see the module
        docstring)."""
        return inspect_session(_Source(self.blobs, sid))

    def take_over(self, sid: str, *, unless: Iterable[str] = ()) -> SessionRecord | Damage:
        """Session ``sid`` read back, checked, and owned from now on: its lease is taken by
        writing the manifest read back with the lease's epoch + 1 and this instance as its
        owner, conditionally on the manifest's ETag as read, so that of several instances
        taking it at once one wins (the others get :class:`Fenced`), and the previous owner's
        next commit is fenced. A damaged session is held without a write (its operations are
        refused but for a repair, itself conditional, and a deletion). FileNotFoundError if
        it has no manifest; :class:`Fenced` if its lease names an owner in ``unless`` (the
        live instances: one took it over already)."""
        src = _Source(self.blobs, sid)
        got = inspect_session(src)
        if src.manifest is None:
            if src.manifest_seen:
                raise FileNotFoundError(sid)
            raise StoreError(f"session {sid!r}: its manifest cannot be read")
        data, etag = src.manifest
        holder = (lease_of(data) or {}).get("owner")
        if holder is not None and holder != self.owner and holder in set(unless):
            raise Fenced(f"session {sid!r} is owned by live instance {holder!r}")
        prev = named_in(self._previous_manifest(sid))
        if isinstance(got, Damage):
            with self._lock:
                self._heads[sid] = _Head(etag, data, named_in(data), prev, lease_of(data))
            return got
        old = lease_of(data) or {}
        lease = self._new_lease(int(old.get("epoch", 0)) + 1)
        body = decode_manifest(data)
        body["lease"] = lease
        data = encode_manifest(body)
        try:
            etag = (self.blobs.put_if_match(_key(sid, MANIFEST), data, etag) if etag is not None
                    else self.blobs.put(_key(sid, MANIFEST), data))
        except PreconditionFailed:
            raise Fenced(f"session {sid!r} changed while it was taken over") from None
        with self._lock:
            self._heads[sid] = _Head(etag, data, got.named_files(), prev, lease)
        log.info("session %s: lease taken (epoch %d, previous owner %s)", sid, lease["epoch"],
                 old.get("owner"))
        return got

    def exists(self, sid: str) -> bool:
        """Whether session ``sid`` has a manifest in the store (True when that cannot be
        read: the store, not the session, failed)."""
        try:
            data, _ = self.blobs.get(_key(sid, MANIFEST))
        except FileNotFoundError:
            return False
        except OSError:
            return True
        return not is_tombstone(data)

    def still_owned(self, sid: str) -> bool:
        """Whether the manifest of ``sid`` is still the one this instance last read or wrote
        (False: another instance took the session over, or it is gone)."""
        with self._lock:
            head = self._heads.get(sid)
        if head is None:
            return False
        try:
            _, etag = self.blobs.get(_key(sid, MANIFEST))
        except FileNotFoundError:
            return False
        return etag == head.etag

    def lease(self, sid: str) -> dict[str, Any] | None:
        """The lease recorded in the store for ``sid`` (None: none, or unreadable)."""
        try:
            return lease_of(self.blobs.get(_key(sid, MANIFEST))[0])
        except OSError:
            return None

    def load_all(self) -> tuple[list[SessionRecord], list[Damage]]:
        """Every session in the store, checked and taken over (:meth:`take_over`): the intact
        ones, and the damaged ones with what is wrong (none is skipped). Removes old
        leftovers of interrupted writes. (An instance of a fleet takes sessions one by one
        instead, those no live instance owns.)"""
        return load_each(self.session_ids(), self._taken_over, self._collect_unnamed)

    def _taken_over(self, sid: str) -> SessionRecord | Damage | None:
        """:meth:`take_over` for :meth:`load_all`: None (left out) for a session that never
        committed or is half deleted (its leftovers collected) or another instance writes."""
        try:
            return self.take_over(sid)
        except FileNotFoundError:  # a create that never committed, or a delete half done
            self._collect(sid, set())
        except Fenced:
            log.warning("session %s is being written by another instance: not loaded", sid)
        return None

    def _collect_unnamed(self, sid: str, record: SessionRecord) -> None:
        head = self._heads.get(sid)
        if head is not None:
            self._collect(sid, head.named | head.previous)

    def _previous_manifest(self, sid: str) -> bytes | None:
        try:
            return self.blobs.get(_key(sid, PREVIOUS))[0]
        except OSError:
            return None

    def _collect(self, sid: str, keep: set[str]) -> None:
        """Remove the session's objects that ``keep`` does not name (nor a manifest), older
        than :data:`LEFTOVER_AGE`."""
        prefix = f"{SESSIONS}{sid}/"
        old = time.time() - LEFTOVER_AGE
        try:
            found = self.blobs.list(prefix)
        except OSError as exc:
            log.warning("could not list %s: %s", prefix, exc)
            return
        self._remove(b.key for b in found if b.modified < old
                     and b.key[len(prefix):] not in keep | {MANIFEST, PREVIOUS})

    # ------------------------------------------------------------------ repair
    def repair(self, sid: str) -> Repair:
        """Bring damaged session ``sid`` back as
        :meth:`~agilegs.service.store.write.SessionStore.repair` does; the new version is
        committed against the manifest read (:class:`Fenced` if it changed meanwhile)."""
        with self._lock:
            known = self._heads.get(sid)
        src = _Source(self.blobs, sid)
        got = inspect_session(src)
        if not isinstance(got, Damage):
            return Repair(got, None, (), repaired=False)
        target = got.record
        if not isinstance(target, SessionRecord):
            raise StoreError(f"session {sid!r}: {got.plan()}")
        if known is not None:
            head = known
        else:
            data, etag = src.manifest if src.manifest is not None else (None, None)
            head = _Head(etag, data, named_in(data), named_in(self._previous_manifest(sid)))
        bad = set(got.frame_files)
        views = tuple(without_files(v, bad) for v in target.views)
        seen = [target.version, got.version or 0, *self._object_versions(sid)]
        new = replace(target, version=max(seen) + 1, updated_at=time.time(), views=views)
        new, etag, data = self._write_version(sid, head, new, ("warm",), {},
                                              head.lease or lease_of(head.manifest),
                                              keep_previous=False)
        named = new.named_files()
        with self._lock:
            self._heads[sid] = _Head(etag, data, named, head.previous, head.lease)
        log.warning("session %s repaired: %s; now version %d", sid, got.plan(), new.version)
        return Repair(new, got.rollback_to, got.drop_frames)

    def _object_versions(self, sid: str) -> list[int]:
        prefix = f"{SESSIONS}{sid}/"
        out = []
        for b in self.blobs.list(prefix):
            hit = _ROLE_OBJECT.match(b.key[len(prefix):])
            if hit:
                out.append(int(hit.group(2)))
        return out


def _renamed(view: ViewRecord, names: dict[str, str]) -> ViewRecord:
    changes: dict[str, Any] = {}
    if view.image_file in names:
        changes["image_file"] = names[view.image_file]
    if view.depth_file in names:
        changes["depth_file"] = names[view.depth_file]
    return replace(view, **changes) if changes else view


AnyStore = SessionStore | ObjectSessionStore
"""A session store: a state folder, or an object store."""


def open_store(state: str | Path, *, fsync: bool = True, endpoint: str | None = None
               ) -> AnyStore:
    """The session store at ``state``: ``s3://bucket/prefix`` (an object store; ``endpoint``:
    its S3 API's URL, default ``AWS_ENDPOINT_URL``), ``file:///path`` or a path (a state
    folder, ``fsync`` as :class:`~agilegs.service.store.write.SessionStore`)."""
    text = str(state)
    if text.startswith("s3://"):
        return ObjectSessionStore(open_blobs(text, endpoint=endpoint))
    return SessionStore(folder_of(state), fsync=fsync)


def folder_of(state: str | Path) -> Path:
    """The folder of ``file:///path`` or a path; ValueError for another URL."""
    text = str(state)
    if text.startswith("file://"):
        parts = urlsplit(text)
        if parts.netloc not in ("", "localhost"):
            raise ValueError(f"{text!r}: a file:// URL names a local folder (file:///path)")
        return Path(unquote(parts.path))
    if "://" in text:
        raise ValueError(f"{text!r}: the state is a folder (a path or file:///path) or an "
                         "object store (s3://bucket/prefix)")
    return Path(text)

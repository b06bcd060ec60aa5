"""``agilegs store check DIR`` and ``agilegs store repair DIR``: a server's state folder
checked, and its damaged sessions repaired, offline. ``DIR`` may also be an object store's
URL (``s3://bucket/prefix``, the ``--state-url`` of a fleet; ``--endpoint`` or
``AWS_ENDPOINT_URL`` for an S3 API other than AWS): the same checks, reports and repairs
(:mod:`agilegs.service.store.objects`).

``check`` reads every session of the folder back and checks every file against the
checksums of its manifest (:mod:`agilegs.service.store.read`); it changes nothing, and
prints one line per session (``--json``: the ``list_sessions`` entries). Exit status 0 when
every session checks out, 1 when one is damaged, 2 when the folder cannot be read.

``repair`` claims the folder (it refuses while a server holds it: use that server's
``repair_session`` operation instead; an object store has no claim: a repair commits by a
conditional put, so it fails rather than overwrite a change a server made meanwhile) and
repairs each damaged session (:meth:`~agilegs.service.store.write.SessionStore.repair`: roll
back to the previous version, drop damaged frames); ``--dry-run`` prints what it would do.
Exit status 0 when every session checks out afterwards, 1 when one could not be repaired, 2
when the folder cannot be used.

The store (torch) is imported when a command runs, so that ``--help`` answers at once.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from .store.integrity import Damage
from .store.state_dir import (
    StateDirError,
    claim_state_dir,
    describe_holder,
    is_claimed,
    read_holder,
)

if TYPE_CHECKING:
    from .store.objects import AnyStore
    from .store.records import SessionRecord

__all__ = ["add_arguments", "check", "repair", "run", "run_on"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("state_dir", metavar="DIR", help="the server's state folder "
                        "(--state-dir of agilegs serve), or its object store "
                        "(s3://bucket/prefix, --state-url)")
    parser.add_argument("--endpoint", metavar="URL", help="the S3 API of an s3:// store "
                        "(default AWS_ENDPOINT_URL, else AWS)")
    parser.add_argument("--session", action="append", metavar="ID",
                        help="only this session (repeatable)")
    if parser.prog.split()[-1] == "repair":
        parser.add_argument("--dry-run", action="store_true",
                            help="print what would be done, change nothing")
    else:
        parser.add_argument("--json", action="store_true",
                            help="print the list_sessions entries as JSON")


def run(args: argparse.Namespace) -> int:
    if str(args.state_dir).startswith("s3://"):
        return run_on(args.state_dir, args.subcommand, args.session,
                      dry_run=getattr(args, "dry_run", False),
                      as_json=getattr(args, "json", False), endpoint=args.endpoint)
    root = Path(args.state_dir)
    if not root.is_dir():
        sys.stderr.write(f"agilegs store: no state folder at {root}\n")
        return 2
    if args.subcommand == "repair":
        return repair(root, args.session, dry_run=args.dry_run)
    return check(root, args.session, as_json=args.json)


def run_on(url: str, subcommand: str, only: list[str] | None = None, *, dry_run: bool = False,
           as_json: bool = False, endpoint: str | None = None, out: TextIO | None = None
           ) -> int:
    """``check`` or ``repair`` on the object store at ``url`` (``s3://bucket/prefix``)."""
    from .store import objects

    out = out or sys.stdout
    try:
        store = objects.open_store(url, endpoint=endpoint)
        ids = _select(store, only)
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"agilegs store {subcommand}: cannot read {url} ({exc})\n")
        return 2
    if subcommand == "repair":
        return _repair_all(store, ids, dry_run=dry_run, out=out)
    return _report(store.where, [store.inspect(sid) for sid in ids], as_json=as_json, out=out)


def _select(store: AnyStore, only: list[str] | None) -> list[str]:
    ids = store.session_ids(tidy=False)
    return [s for s in ids if s in set(only)] if only else ids


def check(root: Path, only: list[str] | None = None, *, as_json: bool = False,
          out: TextIO | None = None) -> int:
    """Check every session of ``root`` (or those in ``only``); see the module docstring."""
    from .store.write import SessionStore

    out = out or sys.stdout
    store = SessionStore(root)
    try:
        ids = _select(store, only)
    except OSError as exc:
        sys.stderr.write(f"agilegs store check: cannot read {root} ({exc.strerror or exc})\n")
        return 2
    results = [store.inspect(sid) for sid in ids]
    if is_claimed(root) and not as_json:
        holder = read_holder(root)
        out.write(f"note: {describe_holder(holder)} holds {root}; it reports damage itself "
                  "(list_sessions)\n")
    return _report(str(root), results, as_json=as_json, out=out)


def _report(where: str, results: list[SessionRecord | Damage], *, as_json: bool, out: TextIO
            ) -> int:
    from .sessions.listing import damaged_summary, record_summary

    damaged = [r for r in results if isinstance(r, Damage)]
    if as_json:
        entries = [damaged_summary(r) if isinstance(r, Damage) else record_summary(r)
                   for r in results]
        out.write(json.dumps([e.model_dump(mode="json") for e in entries], indent=1) + "\n")
        return 1 if damaged else 0
    out.write(f"{where}: {len(results)} session(s), {len(damaged)} damaged\n")
    for r in results:
        if isinstance(r, Damage):
            out.write(f"  {r.session:<20} damaged  {r.reason()}\n")
            way = r.plan() if r.repairable else f"impossible: {r.plan()}"
            out.write(f"  {'':<20}          repair: {way}\n")
        else:
            out.write(f"  {r.id:<20} ok       version {r.version}, {len(r.views)} views, "
                      f"{len(r.gmap)} Gaussians, pool {len(r.pool_ids)}\n")
    return 1 if damaged else 0


def repair(root: Path, only: list[str] | None = None, *, dry_run: bool = False,
           out: TextIO | None = None) -> int:
    """Repair the damaged sessions of ``root`` (or of those in ``only``); see the module
    docstring."""
    from .store.write import SessionStore

    out = out or sys.stdout
    try:
        lock = claim_state_dir(root, command="agilegs store repair")
    except StateDirError as exc:
        sys.stderr.write(f"agilegs store repair: {exc}\n")
        return 2
    with lock:
        store = SessionStore(root)
        return _repair_all(store, _select(store, only), dry_run=dry_run, out=out)


def _repair_all(store: AnyStore, ids: list[str], *, dry_run: bool, out: TextIO) -> int:
    from .store.write import StoreError

    left = 0
    for sid in ids:
        got = store.inspect(sid)
        if not isinstance(got, Damage):
            continue
        out.write(f"{sid}: damaged: {got.reason()}\n")
        if not got.repairable:
            out.write(f"{sid}: cannot be repaired: {got.plan()}\n")
            left += 1
            continue
        if dry_run:
            out.write(f"{sid}: would {got.plan()}\n")
            left += 1
            continue
        try:
            done = store.repair(sid)
        except (StoreError, OSError) as exc:
            out.write(f"{sid}: repair failed: {exc}\n")
            left += 1
            continue
        out.write(f"{sid}: repaired ({got.plan()}); now version {done.record.version}\n")
    out.write(f"{left} damaged session(s) left\n" if left else "every session checks out\n")
    return 1 if left else 0

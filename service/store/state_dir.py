"""The state folder of one server: checked at start, and held exclusively while it runs.

:func:`claim_state_dir` creates the folder if it is missing, takes an exclusive ``flock`` on
``<state_dir>/agilegs.lock`` and records the holder in that file (command, pid, host,
instance id, start time). Everything that writes the folder claims it first: ``agilegs
serve`` (:class:`~agilegs.service.server.Server`) for as long as it runs, and ``agilegs store
repair``. A second claim on the same folder is refused with a one-line
:class:`StateDirError` naming the holder: two servers on one folder would each hold their own
copy of the sessions and write over each other's files.

The kernel releases the lock when its holder's process ends, however it ends (SIGKILL
included): a killed server never blocks a restart, and the holder it recorded is simply
overwritten. (``flock`` is per open file: over NFS it needs a Linux client with ``flock``
emulated by byte-range locks, the default since 2.6.12.)

A folder that cannot be created, is not a folder, or is read-only is a
:class:`StateDirError` too: the server says so in one line and exits non-zero.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import socket
import time
from pathlib import Path
from typing import Any

from ..errors import is_disk_full

__all__ = ["LOCK_FILE", "StateDirError", "StateLock", "claim_state_dir", "describe_holder",
           "is_claimed", "read_holder"]

log = logging.getLogger(__name__)

LOCK_FILE = "agilegs.lock"


class StateDirError(RuntimeError):
    """The state folder cannot be used (one line: what and why)."""


class StateLock:
    """An exclusive claim on a state folder (see the module docstring); :meth:`release` or
    the end of the process gives it back.

    Attributes:
        root: the state folder.
        holder: what was recorded in the lock file.
    """

    def __init__(self, root: Path, fd: int, holder: dict[str, Any]) -> None:
        self.root = root
        self.holder = holder
        self._fd: int | None = fd

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def __enter__(self) -> StateLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def read_holder(root: Path | str) -> dict[str, Any] | None:
    """What the lock file of ``root`` records (None: nothing readable)."""
    try:
        data = json.loads((Path(root) / LOCK_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def is_claimed(root: Path | str) -> bool:
    """Whether a live process holds ``root`` (tried without writing anything)."""
    try:
        fd = os.open(Path(root) / LOCK_FILE, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # closing the only descriptor drops a lock taken through it
    return False


def describe_holder(holder: dict[str, Any] | None) -> str:
    """``agilegs serve (pid 41 on host lab-3, instance lab-3-8000, since 2025-05-01 ...)``."""
    if not holder:
        return "a process that has not recorded itself yet"
    since = holder.get("started_at")
    when = (time.strftime("%Y-%m-%d %H:%M:%S %Z", time.localtime(float(since)))
            if isinstance(since, (int, float)) else "?")
    parts = [f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}"]
    if holder.get("instance"):
        parts.append(f"instance {holder['instance']}")
    parts.append(f"since {when}")
    return f"{holder.get('command', 'a process')} ({', '.join(parts)})"


def _fail(root: Path, doing: str, exc: OSError) -> StateDirError:
    why = exc.strerror or str(exc)
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return StateDirError(f"the state folder {root} is read-only ({why}): the server must "
                             "be able to write there")
    return StateDirError(f"cannot {doing} the state folder {root} ({why})")


def claim_state_dir(state_dir: Path | str, *, command: str,
                    instance: str | None = None) -> StateLock:
    """Create ``state_dir`` if missing, check it is writable, and claim it exclusively;
    :class:`StateDirError` (one line) if any of that fails, naming the holder of a claim
    already taken.

    Args:
        command: who claims it (``agilegs serve``, ``agilegs store repair``), recorded.
        instance: the server's instance id, recorded.
    """
    root = Path(state_dir)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise StateDirError(f"the state folder {root} is not a folder") from None
    except OSError as exc:
        raise _fail(root, "create", exc) from None
    if not root.is_dir():
        raise StateDirError(f"the state folder {root} is not a folder")
    path = root / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise _fail(root, "open", exc) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
            raise StateDirError(
                f"the state folder {root} is in use by {describe_holder(read_holder(root))}: "
                "stop it first, or give this one another --state-dir") from None
        raise _fail(root, "lock", exc) from None
    lock = StateLock(root, fd, {})
    try:
        _check_writable(root)
        lock.holder = _record(fd, command, instance)
    except BaseException:
        lock.release()
        raise
    return lock


def _check_writable(root: Path) -> None:
    probe = root / "sessions" / f".probe-{os.getpid()}"
    try:
        probe.parent.mkdir(exist_ok=True)
        probe.touch()
        probe.unlink()
    except OSError as exc:
        if is_disk_full(exc):
            log.warning("the state folder %s is full: writes are refused until space is freed",
                        root)
            return
        raise _fail(root, "write to", exc) from None


def _record(fd: int, command: str, instance: str | None) -> dict[str, Any]:
    holder = {"command": command, "pid": os.getpid(), "host": socket.gethostname(),
              "instance": instance, "started_at": time.time()}
    data = (json.dumps(holder) + "\n").encode()
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)
        os.fsync(fd)
    except OSError as exc:  # a full disk: the lock holds all the same
        log.warning("could not record the state folder's holder (%s)", exc.strerror or exc)
    return holder

"""A fleet: instances sharing one object store hand its sessions over by lease.

Each instance of a fleet (``--state-url s3://...`` with Zenoh on) owns some of the store's
sessions. While it owns one it declares the Zenoh liveliness token
``agilegs/@leases/<session>/<instance>`` (beside the session's queryables, see
:mod:`agilegs.service.transports.zenoh.cluster`), and while it is up,
``agilegs/@members/<instance>``. Every instance subscribes to both, so each learns at once
when an owner is gone: its Zenoh session ends (a killed process's links close at once; a
paused or cut-off one's expire with Zenoh's lease, 10 s by default), and its tokens go with
it.

A session whose owner is gone is *orphaned*. One live instance takes it over: the one first
in its rendezvous order (a hash of session and instance id: sessions spread evenly, and every
instance computes the same order) tries at once, the next after :data:`STAGGER` s if the
session is still orphaned, and so on; none takes a session whose lease in the store names a
live instance (one took it over already). Taking over is a conditional write in the store
(:meth:`~agilegs.service.store.objects.ObjectSessionStore.take_over`: the lease's epoch + 1 in
the manifest, ``If-Match`` on the ETag read), so of several instances trying at once exactly
one succeeds; it loads the last committed version, declares the session's queryables and
token, and the mapper resumes from the last committed map. The others see the token and
stand down.

A session in the store that no instance has ever claimed while this one watched (created by
an instance that died before declaring it, or found at start) is orphaned once it has been
without a token for :data:`GRACE` s (a session being created has its token within
milliseconds).

The old owner, if it comes back (a paused process resumed, a partition healed), sees another
instance's token on its session and checks the store: the manifest changed, so it drops the
session and logs that it lost the lease. Whatever it tries to write before it notices is
fenced by the store (its ``If-Match`` fails), answered ``session_unavailable``, and it drops
the session then. Every :data:`CHECK` s each instance also checks that the manifests of its
sessions are still those it last wrote.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from agilegs.schemas.keys import LEASES, MEMBERS, PREFIX, lease_key, member_key, parse_lease_key

if TYPE_CHECKING:
    from ...sessions.registry import SessionRegistry

__all__ = ["CHECK", "GRACE", "SCAN", "STAGGER", "Fleet", "rendezvous_order"]

log = logging.getLogger(__name__)

TICK = 0.1
"""Seconds between two looks at the orphaned sessions."""
SCAN = 1.0
"""Seconds between two listings of the store's sessions."""
GRACE = 3.0
"""Seconds a session found in the store without any owner's token waits before it is
orphaned (one whose owner's token was seen to go is orphaned at once)."""
STAGGER = 0.5
"""Seconds between the takeover attempts of the instances in a session's rendezvous order."""
CHECK = 2.0
"""Seconds between two checks that this instance's sessions are still its own."""


def rendezvous_order(session: str, instances: set[str]) -> list[str]:
    """The instances in the order they try to take ``session`` over (highest random weight:
    every instance computes the same order, and sessions spread evenly)."""
    def weight(iid: str) -> bytes:
        return hashlib.sha256(f"{session}\0{iid}".encode()).digest()

    return sorted(instances, key=weight, reverse=True)


class Fleet:
    """This instance's part of a fleet (see the module docstring).

    Args:
        registry: this instance's sessions (an object store under them).
        instance_id: this instance's id.
        on_change: called after sessions were taken over or dropped (declares or undeclares
            their queryables: the cluster's ``sync``).
    """

    def __init__(self, registry: SessionRegistry, instance_id: str,
                 on_change: Callable[[], None]) -> None:
        self.registry = registry
        self.instance_id = instance_id
        self.on_change = on_change
        self._z: Any = None
        self._entities: list[Any] = []
        self._tokens: dict[str, Any] = {}  # session -> its token
        self._owners: dict[str, set[str]] = {}  # session -> instances whose token is up
        self._members: set[str] = {instance_id}
        self._orphans: dict[str, float] = {}  # session -> since when (monotonic)
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._recheck = False
        self._thread: threading.Thread | None = None
        self.takeovers = 0

    # ------------------------------------------------------------------ lifecycle
    def attach(self, zsession: Any) -> None:
        self._z = zsession
        live = zsession.liveliness()
        self._entities.append(live.declare_token(member_key(self.instance_id)))
        for where in (f"{PREFIX}/{LEASES}/**", f"{PREFIX}/{MEMBERS}/*"):
            self._entities.append(live.declare_subscriber(where, self._on_token, history=True))
        self.sync_tokens()
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="agilegs-fleet", daemon=True)
        self._thread.start()
        log.info("fleet: instance %r shares %s", self.instance_id, self.registry.store.where)

    def detach(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None
        with self._lock:
            entities = list(self._tokens.values()) + self._entities
            self._tokens.clear()
            self._entities = []
            self._z = None
        for entity in reversed(entities):
            try:
                entity.undeclare()
            except Exception:
                log.debug("undeclare failed", exc_info=True)

    def owned(self, session: str) -> bool:
        """Whether some instance's token says it owns ``session`` now."""
        with self._lock:
            return bool(self._owners.get(session))

    # ------------------------------------------------------------------ tokens
    def sync_tokens(self) -> None:
        """Declare the token of every session held here, undeclare those of the others."""
        with self._lock:
            z = self._z
            if z is None:
                return
            want = self.registry.held()
            for sid in sorted(set(self._tokens) - want):
                try:
                    self._tokens.pop(sid).undeclare()
                except Exception:
                    log.debug("undeclare failed", exc_info=True)
            for sid in sorted(want - set(self._tokens)):
                self._tokens[sid] = z.liveliness().declare_token(
                    lease_key(sid, self.instance_id))

    def _on_token(self, sample: Any) -> None:
        try:
            sid, owner = parse_lease_key(str(sample.key_expr))
        except ValueError:
            return
        gone = str(sample.kind).upper().endswith("DELETE")
        now = time.monotonic()
        with self._lock:
            if sid == MEMBERS:
                (self._members.discard if gone else self._members.add)(owner)
                if gone:
                    self._members.add(self.instance_id)
                return
            owners = self._owners.setdefault(sid, set())
            if gone:
                owners.discard(owner)
                if not owners and owner != self.instance_id:
                    self._orphans[sid] = now - GRACE  # its owner died: orphaned at once
                    self._wake.set()
            else:
                owners.add(owner)
                self._orphans.pop(sid, None)
                if owner != self.instance_id and self.registry.holds(sid):
                    self._recheck = True  # another instance claims a session held here
                    self._wake.set()

    # ------------------------------------------------------------------ the loop
    def _loop(self) -> None:
        last_scan = last_check = 0.0
        while not self._stop.is_set():
            self._wake.wait(TICK)
            self._wake.clear()
            now = time.monotonic()
            try:
                if self._recheck or now - last_check >= CHECK:
                    self._recheck = False
                    last_check = now
                    if self.registry.check_leases():
                        self.on_change()
                if now - last_scan >= SCAN:
                    last_scan = now
                    self._scan(now)
                self._take_orphans(now)
            except Exception:
                log.exception("fleet: a round of takeovers failed")

    def _scan(self, now: float) -> None:
        """Note the sessions of the store that no instance owns."""
        ids = set(self.registry.store.session_ids())
        held = self.registry.held()
        with self._lock:
            for sid in list(self._orphans):
                if sid not in ids:
                    self._orphans.pop(sid)
            for sid in ids - held:
                if not self._owners.get(sid):
                    self._orphans.setdefault(sid, now)

    def _take_orphans(self, now: float) -> None:
        with self._lock:
            members = set(self._members)
            due = []
            for sid, since in self._orphans.items():
                if self._owners.get(sid):
                    continue
                order = rendezvous_order(sid, members)
                rank = order.index(self.instance_id) if self.instance_id in order else 0
                if now - since >= GRACE + rank * STAGGER:
                    due.append(sid)
        taken = False
        for sid in due:
            with self._lock:
                if self._owners.get(sid):
                    continue
            if self.registry.take_over(sid, live=members):
                taken = True
                self.takeovers += 1
                log.info("fleet: took session %s over (live: %s)", sid, ", ".join(sorted(members)))
            with self._lock:
                self._orphans.pop(sid, None)
        if taken:
            self.on_change()

"""Several ``agilegs serve`` instances as one service, with Zenoh as the distributed engine.

Nothing here is a home-made consensus or directory: ownership is *which instance declares
the Zenoh queryables of a session*, and Zenoh routes every query to whoever declares a
matching queryable.

Ownership
    Each instance owns the sessions it created (they live in its ``--state-dir``). For each
    one it declares the queryable ``agilegs/<session>/*`` and the subscribers
    ``agilegs/<session>/frames`` and ``agilegs/<session>/candidates``; deleting the session
    undeclares them. A killed instance's declarations vanish with its Zenoh session, so
    queries for its sessions find no queryable: the Zenoh client raises
    :class:`~agilegs.client.errors.SessionUnavailableError` and HTTP answers 404
    ``session_unavailable`` ("no instance answers for session X"). (A lone server, one that
    connects to no other node and has not seen another instance since it started, answers
    an unknown session with 404 ``not_found`` as before.) Restarted on the same state folder,
    the instance loads its sessions and declares them again: they are found again.

Instances
    Each instance has an id (``--instance-id`` / ``AGILEGS_INSTANCE_ID``, by default
    ``<hostname>-<http port>``; two live instances may not share one: the second refuses to
    start) and declares ``agilegs/@instances/<id>/health``, ``.../create_session`` (creates
    the session on this instance, whatever the policy says) and ``.../list_sessions`` (this
    instance's sessions only). A get on ``agilegs/@instances/*/health`` enumerates the live
    instances (the reply key names the instance, the :class:`~agilegs.schemas.sessions.Health`
    body carries its load, ``sessions``).

Placement (creating a session without naming an instance)
    The session goes to the live instance with the fewest sessions, ties broken by the
    smallest instance id (:func:`placement_order`); an instance that refuses for a count
    limit (429) passes it to the next one. ``instance=<id>`` (``POST /v1/sessions?instance=<id>``,
    ``agilegs/@service/create_session?instance=<id>``, ``ZenohClient.create_session(...,
    instance=...)``) places it there (404 ``instance_unavailable`` if no such instance
    answers). A session id already owned by a live instance is refused (409) before placing.

``agilegs/@service/*`` with several instances
    Every instance declares the ``@service`` queryables, and Zenoh hands a query to all of
    them. ``health`` is answered by each (a client keeps the first reply). ``create_session``
    and ``list_sessions`` are answered by one instance only, the *coordinator*: the live
    instance with the smallest id; the others drop the query without a reply. The
    coordinator places a new session by the policy above and answers ``list_sessions`` with
    every instance's sessions merged.

HTTP on any instance
    An operation on a session that this instance does not own is forwarded over Zenoh (a get
    on ``agilegs/<session>/<op>``): a JSON or msgpack body (or none) goes as it came, in its
    media type, and the owner's answer (or error reply: its status, code, message and field)
    comes back as it came, neither decoded nor validated here (the owner does both); the
    fields of a request given as query parameters, or a raw .ply / .splat upload, are
    validated here and go as the msgpack body a Zenoh client would send. ``POST
    /v1/sessions`` places the session as above; ``GET /v1/sessions`` merges every live
    instance's sessions (a session appears once); ``/healthz`` and ``/metrics`` describe this
    instance only.

Topology
    Instances reach each other through Zenoh: as clients of a router, or as peers each
    connected to every other one (peers do not route for peers); docs/deploy.md says how.

A fleet (the sessions in an object store, ``--state-url s3://...``): an instance owns the
sessions whose lease it holds, not those it created, and a live instance takes over the
sessions of one that died (:mod:`agilegs.service.transports.zenoh.fleet`); creating a session is a
conditional create in the store, so of two instances creating one id at once exactly one
succeeds. Known limits of instances with state folders of their own: two instances creating
the same explicit session id at the same moment may both succeed (the check-then-create is
not atomic); a session created while an instance that owns the same id is down collides with
it when that instance comes back (both declare it; avoid reusing ids). Instances sharing a
token (``AGILEGS_TOKEN``) forward with it; all instances of a cluster must use the same
token.
"""

from __future__ import annotations

import logging
import re
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ValidationError

from agilegs import schemas as m
from agilegs.client.zenoh_rpc import Answer, first_answer, query
from agilegs.schemas import OPERATIONS, ErrorBody, Operation, codec, keys
from agilegs.schemas.keys import (
    INSTANCE_ID_PATTERN,
    INSTANCE_OPS,
    INSTANCES,
    check_instance_id,
    instance_key,
    instances_wildcard,
    parse_instance_key,
)
from agilegs.schemas.requests import REQUEST_ID_PARAM, session_id_for

from ...errors import ServiceError
from ..gateway import Forwarded
from .fleet import Fleet
from .placement import (
    default_instance_id,
    instance_unavailable,
    placement_order,
    session_queryable_key,
    session_unavailable,
)

if TYPE_CHECKING:
    from concurrent.futures import Executor

    from ..sessions.registry import SessionRegistry
    from ..settings import Settings

__all__ = [
    "INSTANCES",
    "INSTANCE_ID_PATTERN",
    "INSTANCE_OPS",
    "ClusterNode",
    "check_instance_id",
    "instance_key",
    "instances_wildcard",
    "parse_instance_key",
]

log = logging.getLogger(__name__)

PROBE_TIMEOUT = 2.0
"""Seconds to wait for the live instances' health replies (they answer inline)."""

SYNC_INTERVAL = 1.0
"""Seconds between two checks that the declared sessions match the loaded ones."""

_SESSION_RE = re.compile(m.SESSION_ID_PATTERN)

# on_query(query, op, session, local, reply_key): the Zenoh adapter's answering entry point
QueryHandler = Callable[[Any, str, "str | None", bool, "str | None"], None]


# ============================================================================ the node
class ClusterNode:
    """This instance's part of the cluster: its id, the Zenoh declarations of the sessions it
    owns, placement, and forwarding of what it does not own (see the module docstring).

    The gateway routes every operation through :meth:`route`. Until :meth:`attach` is given
    a Zenoh session (and after :meth:`detach`), everything runs locally, as on a single server.

    Args:
        registry: this instance's sessions.
        settings: ``instance_id`` (default :func:`default_instance_id` of the host and the HTTP
            port), ``forward_timeout`` (seconds a forwarded operation may take), ``token``.
        executor: where ``@service`` queries are answered (the gateway's worker threads).
    """

    def __init__(self, registry: SessionRegistry, settings: Settings, executor: Executor
                 ) -> None:
        self.registry = registry
        self.executor = executor
        self.settings = settings
        given = getattr(settings, "instance_id", None)
        self.instance_id = check_instance_id(
            given if given else default_instance_id(port=settings.port), "instance_id")
        self.forward_timeout = float(getattr(settings, "forward_timeout", 120.0))
        token = settings.token_value()
        self._attachment = f"Bearer {token}".encode() if token else None
        self._z: Any = None
        self._on_query: QueryHandler | None = None
        self._on_session_query: Callable[[Any], None] | None = None
        self._on_sample: Callable[[Any], None] | None = None
        self._fixed: list[Any] = []  # @service and @instances queryables
        self._owned: dict[str, list[Any]] = {}  # session -> its declarations
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._syncer: threading.Thread | None = None
        self._seen_others = False
        self.fleet: Fleet | None = None  # sessions handed over by lease (an object store)
        registry.set_owner(self.instance_id)

    # ------------------------------------------------------------------ lifecycle
    def attach(self, zsession: Any, *, on_query: QueryHandler,
               on_session_query: Callable[[Any], None], on_sample: Callable[[Any], None]
               ) -> None:
        """Start answering on ``zsession``: refuse a taken instance id, declare the
        ``@service`` and ``@instances/<id>`` queryables and every loaded session's.

        Args:
            zsession: an open ``zenoh.Session``.
            on_query: answers ``(query, op, session, local, reply_key)``.
            on_session_query: answers a query on ``agilegs/<session>/<op>``.
            on_sample: takes a sample published on a session's frames / candidates.
        """
        self._z = zsession
        self._on_query, self._on_session_query, self._on_sample = (
            on_query, on_session_query, on_sample)
        if self._remote_replies(instance_key(self.instance_id, "health"), PROBE_TIMEOUT):
            self._z = None
            raise RuntimeError(f"instance id {self.instance_id!r} is taken by a live instance: "
                               "give each instance its own --instance-id")
        for op in keys.SERVICE_OPS:
            self._fixed.append(zsession.declare_queryable(
                keys.service_key(op), lambda q, op=op: self._on_service_query(q, op)))
        for op in INSTANCE_OPS:
            reply_key = instance_key(self.instance_id, op)
            self._fixed.append(zsession.declare_queryable(
                reply_key, lambda q, op=op, rk=reply_key: on_query(q, op, None, True, rk)))
        self.sync()
        if self.registry.fleet:
            self.fleet = Fleet(self.registry, self.instance_id, self.sync)
            self.fleet.attach(zsession)
        self._stop.clear()
        self._syncer = threading.Thread(target=self._sync_loop, name="agilegs-cluster-sync",
                                         daemon=True)
        self._syncer.start()
        log.info("cluster: instance %r serves %d session(s)", self.instance_id, len(self._owned))

    def detach(self) -> None:
        """Undeclare everything this node declared (before the Zenoh session closes)."""
        if self.fleet is not None:
            self.fleet.detach()
            self.fleet = None
        self._stop.set()
        if self._syncer is not None:
            self._syncer.join(timeout=10)
            self._syncer = None
        with self._lock:
            entities = [e for ents in self._owned.values() for e in ents] + self._fixed
            self._owned.clear()
            self._fixed = []
            self._z = None
        for entity in reversed(entities):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)

    @property
    def attached(self) -> bool:
        return self._z is not None

    def owned(self) -> list[str]:
        """The sessions whose queryables this instance declares now."""
        with self._lock:
            return sorted(self._owned)

    # ------------------------------------------------------------------ ownership
    def sync(self) -> None:
        """Declare the sessions loaded in the core and not declared yet; undeclare those
        gone (runs after every create / delete, and every :data:`SYNC_INTERVAL` s)."""
        with self._lock:
            z = self._z
            if z is None:
                return
            want = self.registry.held()  # damaged sessions too: their owner answers for them
            for sid in sorted(set(self._owned) - want):
                for entity in self._owned.pop(sid):
                    try:
                        entity.undeclare()
                    except Exception:
                        log.debug("undeclare failed", exc_info=True)
                log.debug("cluster: %s no longer served here", sid)
            assert self._on_session_query is not None and self._on_sample is not None
            for sid in sorted(want - set(self._owned)):
                self._owned[sid] = [
                    z.declare_queryable(session_queryable_key(sid), self._on_session_query,
                                        complete=True),
                    z.declare_subscriber(keys.session_key(sid, keys.FRAMES), self._on_sample),
                    z.declare_subscriber(keys.session_key(sid, keys.CANDIDATES), self._on_sample),
                ]
                log.debug("cluster: %s served here", sid)
        if self.fleet is not None:
            self.fleet.sync_tokens()

    def _sync_loop(self) -> None:
        ticks = 0
        while not self._stop.wait(SYNC_INTERVAL):
            ticks += 1
            try:
                self.sync()
                if not self._seen_others and ticks % 5 == 0:
                    self.instances()  # notices a cluster that only ever calls in
            except Exception:
                log.exception("cluster: declaring sessions failed")

    # ------------------------------------------------------------------ membership
    def instances(self, timeout: float = PROBE_TIMEOUT) -> dict[str, m.Health]:
        """The live instances (this one included): id -> its health (``sessions``: load)."""
        out: dict[str, m.Health] = {}
        for key, data in self._remote_replies(instances_wildcard("health"), timeout):
            try:
                iid, _ = parse_instance_key(key)
                out[iid] = m.Health.model_validate(data)
            except (ValueError, ValidationError):
                log.warning("cluster: ignoring a malformed health reply on %s", key)
        out[self.instance_id] = self.registry.health()
        if len(out) > 1:
            self._seen_others = True
        return out

    @property
    def in_cluster(self) -> bool:
        """Whether this instance is part of a cluster: it connects to other Zenoh nodes, or
        it has seen another instance since it started. A session that no instance answers
        for is then ``session_unavailable`` (its owner may be down), not ``not_found``."""
        return bool(self.settings.zenoh_connect) or self._seen_others or self.fleet is not None

    def coordinator(self) -> str:
        """The live instance that answers ``@service`` creates and listings: the smallest id."""
        return min(self.instances())

    # ------------------------------------------------------------------ dispatch
    def route(self, op: str, session: str | None, req: BaseModel | None, *,
              run_local: Callable[[], BaseModel], instance: str | None = None,
              local: bool = False, request_id: str | None = None) -> BaseModel:
        """Run a validated request where it belongs: ``run_local`` here, or forwarded to the
        instance that owns the session (the owner's refusal is re-raised with its status,
        code, message and field).

        Args:
            instance: for ``create_session``, the instance to create it on (else the policy).
            local: run it here whatever the cluster holds (queries on ``@instances/<me>``).
            request_id: a write's request id, forwarded with it (a ``create_session``
                without ``id`` creates :func:`~agilegs.schemas.requests.session_id_for` it).
        """
        spec = OPERATIONS[op]
        if local:
            return self._local(op, run_local)
        if instance is not None and op == "create_session":
            try:
                check_instance_id(instance)
            except ValueError as exc:
                raise ServiceError(422, "invalid", str(exc), "query.instance") from None
        if spec.scope == "session":
            if (self._z is None or session is None or not _SESSION_RE.match(session)
                    or self.registry.holds(session)):
                return self._local(op, run_local)
            return self._forward_session(spec, session, req, run_local, request_id)
        if op == "list_sessions" and self._z is not None:
            return self._merged_list()
        if op == "create_session" and self._z is not None:
            assert isinstance(req, m.SessionCreate)
            if request_id is not None and req.id is None:  # named by its request id
                req.id = session_id_for(request_id)
                if (mine := self._created_elsewhere(req.id)) is not None:
                    return mine
            body = codec.dump(req, codec.MSGPACK)
            self._check_id_free(req.id)
            if instance is None:
                return self._place(body, run_local, request_id)
            if instance != self.instance_id:
                return self._create_on(instance, body, request_id)
        elif op == "create_session" and instance not in (None, self.instance_id):
            raise instance_unavailable(str(instance))
        return self._local(op, run_local)

    def _local(self, op: str, run_local: Callable[[], BaseModel]) -> BaseModel:
        result = run_local()
        if op in ("create_session", "delete_session"):
            self.sync()  # declared before the reply leaves: the session is found at once
        return result

    def owned_elsewhere(self, op: str, session: str | None) -> bool:
        """Whether ``op`` is a session operation on a session this instance does not hold
        while it is in a Zenoh session (it is then forwarded to the owner)."""
        return (OPERATIONS[op].scope == "session" and self._z is not None
                and session is not None and _SESSION_RE.match(session) is not None
                and not self.registry.holds(session))

    def forward_bytes(self, op: str, session: str, body: bytes | None, kind: str,
                      request_id: str | None = None) -> Forwarded | None:
        """The owner's answer to ``op`` with ``body`` (media type ``kind``; without a body the
        answer comes in ``kind``), as it came; None when no instance answers and this one is
        not in a cluster (a lone server: the session does not exist, and it says so)."""
        spec = OPERATIONS[op]
        sent_to_owner = self.fleet is not None and self.fleet.owned(session)
        ans = self._ask(keys.session_key(session, op), body, spec, kind, request_id)
        if ans is not None:
            return Forwarded(ans.ok, ans.payload, ans.kind)
        live = sorted(self.instances())
        if not self.in_cluster or not self._may_exist(session):
            return None
        raise self._unanswered(spec, session, live, sent_to_owner, request_id)

    def _forward_session(self, spec: Operation, session: str, req: BaseModel | None,
                         run_local: Callable[[], BaseModel], request_id: str | None
                         ) -> BaseModel:
        body = codec.dump(req, codec.MSGPACK) if req is not None else None
        sent_to_owner = self.fleet is not None and self.fleet.owned(session)
        got = self._forward(keys.session_key(session, spec.name), body, spec, request_id)
        if got is not None:
            return got
        live = sorted(self.instances())
        if not self.in_cluster or not self._may_exist(session):  # it simply does not exist
            return self._local(spec.name, run_local)
        raise self._unanswered(spec, session, live, sent_to_owner, request_id)

    def _unanswered(self, spec: Operation, session: str, live: list[str], sent_to_owner: bool,
                    request_id: str | None = None) -> ServiceError:
        """The error of an operation no instance answered. In a fleet it is retryable
        (``retry_after``) unless it may have changed the session and carries no request id:
        a write that went to an owner that then went away may have been committed (503, no
        ``retry_after``: read the session to know). With a request id its retry applies it
        once (the new owner finds the id in the committed record when it was applied)."""
        if (self.fleet is not None and sent_to_owner and spec.http_method != "GET"
                and request_id is None):
            return ServiceError(
                503, "unavailable", f"{spec.name}: the instance that owned session "
                f"{session!r} went away while answering; the change may or may not have been "
                "made: read the session to know", "path.session")
        return session_unavailable(session, live, fleet=self.fleet is not None)

    def _may_exist(self, session: str) -> bool:
        """Whether a session no instance answers for may exist (in a fleet: in the store)."""
        return self.fleet is None or self.registry.in_store(session)

    def _create_on(self, instance: str, body: bytes | None, request_id: str | None
                   ) -> BaseModel:
        got = self._forward(instance_key(instance, "create_session"), body,
                            OPERATIONS["create_session"], request_id)
        if got is None:
            raise instance_unavailable(instance)
        return got

    def _check_id_free(self, sid: str | None) -> None:
        """409 if the requested session id is held here or by another live instance."""
        if sid is not None and (self.registry.holds(sid) or self._remote_replies(
                keys.session_key(sid, "get_session"), PROBE_TIMEOUT)):
            raise ServiceError(409, "conflict", f"session {sid!r} already exists", "body.id")

    def _created_elsewhere(self, sid: str) -> BaseModel | None:
        """The session ``sid`` as another live instance answers it, when one holds it: a
        create whose id comes from its request id finds there the session it created
        already (an earlier attempt whose answer was lost); None when none holds it."""
        if self.registry.holds(sid):
            return None
        return self._forward(keys.session_key(sid, "get_session"), None,
                             OPERATIONS["get_session"])

    def _place(self, body: bytes, run_local: Callable[[], BaseModel], request_id: str | None
               ) -> BaseModel:
        spec = OPERATIONS["create_session"]
        loads = {iid: h.sessions for iid, h in self.instances().items()}
        refusal: ServiceError | None = None
        for target in placement_order(loads):
            try:
                if target == self.instance_id:
                    return self._local(spec.name, run_local)
                got = self._forward(instance_key(target, "create_session"), body, spec,
                                    request_id)
            except ServiceError as err:
                if err.status != 429:
                    raise
                refusal = err  # full: try the next instance
                continue
            if got is not None:
                log.info("cluster: session placed on %s", target)
                return got
        raise refusal or ServiceError(503, "unavailable", "no instance could take the session")

    def _merged_list(self) -> m.SessionList:
        out = list(self.registry.list_sessions().sessions)
        seen = {s.id for s in out}
        for key, data in self._remote_replies(instances_wildcard("list_sessions"),
                                              min(self.forward_timeout, 10.0)):
            try:
                more = m.SessionList.model_validate(data).sessions
            except ValidationError:
                log.warning("cluster: ignoring a malformed session list from %s", key)
                continue
            for s in more:
                if s.id not in seen:
                    seen.add(s.id)
                    out.append(s)
        return m.SessionList(sessions=out)

    # ------------------------------------------------------------------ Zenoh gets
    def _remote_replies(self, key: str, timeout: float) -> list[tuple[str, Any]]:
        """The decoded ok replies of other instances to a get on ``key`` (errors skipped)."""
        z = self._z
        if z is None:
            return []
        out = []
        try:
            for ans in query(z, key, timeout=timeout, attachment=self._attachment,
                             remote_only=True, every_reply=True):
                if not ans.ok:
                    continue
                try:
                    out.append((ans.key, ans.load()))
                except codec.DecodeError:
                    log.warning("cluster: undecodable reply on %s", key)
        except Exception:
            log.warning("cluster: get on %s failed", key, exc_info=True)
        return out

    def _ask(self, key: str, body: bytes | None, spec: Operation, kind: str = codec.MSGPACK,
             request_id: str | None = None) -> Answer | None:
        """The first answer of another instance to ``spec`` on ``key`` (``body`` in media
        type ``kind``, ``request_id`` as its parameter); None when no instance answers;
        502 / 504 when the get fails or times out."""
        z = self._z
        if z is None:
            return None
        params = f"{REQUEST_ID_PARAM}={request_id}" if request_id is not None else None
        try:
            ans, timed_out = first_answer(z, key, payload=body, attachment=self._attachment,
                                          timeout=self.forward_timeout, remote_only=True,
                                          every_reply=True, encoding=kind, parameters=params)
        except Exception as exc:
            raise ServiceError(502, "bad_gateway", f"{spec.name}: forwarding on {key} failed "
                               f"({type(exc).__name__}: {exc})") from exc
        if ans is None and timed_out:
            raise ServiceError(504, "gateway_timeout", f"{spec.name}: the instance that "
                               f"owns it did not answer within {self.forward_timeout:g} s")
        return ans

    def _forward(self, key: str, body: bytes | None, spec: Operation,
                 request_id: str | None = None) -> BaseModel | None:
        """The owner's answer to ``spec`` on ``key`` (a msgpack ``body``), validated; None
        when no instance answers."""
        ans = self._ask(key, body, spec, codec.MSGPACK, request_id)
        if ans is None:
            return None
        if ans.ok:
            try:
                return spec.response.model_validate(ans.load())
            except (codec.DecodeError, ValidationError) as exc:
                raise ServiceError(502, "bad_gateway", f"{spec.name}: the owner's answer "
                                   f"on {key} is malformed: {exc}") from None
        try:
            info = ErrorBody.model_validate(ans.load()).error
        except (codec.DecodeError, ValidationError):
            raise ServiceError(502, "bad_gateway", f"{spec.name}: the owner's error "
                               f"reply on {key} is malformed") from None
        raise ServiceError(info.status, info.code, info.message, info.field, list(info.errors),
                           info.supported)

    # ------------------------------------------------------------------ @service queries
    def _on_service_query(self, query: Any, op: str) -> None:
        """``agilegs/@service/<op>``: every instance answers ``health``; only the coordinator
        answers the rest (the others drop the query without a reply)."""
        on_query = self._on_query
        assert on_query is not None
        if op == "health":
            on_query(query, op, None, False, None)
            return
        try:
            self.executor.submit(self._answer_if_coordinator, query, op)
        except RuntimeError:  # stopping: let the adapter say so
            on_query(query, op, None, False, None)

    def _answer_if_coordinator(self, query: Any, op: str) -> None:
        try:
            lead = self.coordinator()
        except Exception:
            log.exception("cluster: could not enumerate the instances")
            lead = self.instance_id
        if lead != self.instance_id:
            query.drop()
            return
        assert self._on_query is not None
        self._on_query(query, op, None, False, None)

"""The ROS 2 transport: agilegs' topics and services as zenoh-bridge-ros2dds carries them
(CDR payloads on the keys of :mod:`agilegs.client.ros2.keys`), as glue over the gateway.

Every namespace it serves has one worker thread that handles, in arrival order (the order
Zenoh received them), the namespace's topic messages and service requests, so that a frame
published before a ``select`` request is applied before the selection. A message becomes a gateway
:class:`~agilegs.service.transports.gateway.Request` (transport ``ros2``) with a body built by
:mod:`.convert`: authentication, validation, errors, persistence, metrics and decision hooks
are the ones of HTTP and Zenoh.

* **Services** (``create_session``, ``open_session``, ``select``): the request's ``token``
  is checked first (as an HTTP ``Authorization`` header is); the reply is always the
  service's response, its ``status`` saying 200 or why not (the bridge cannot hand a Zenoh
  error reply to a ROS client, which would wait until its timeout). A successful
  ``create_session`` or ``open_session`` binds the namespace to the session.
* **Topics** act on the session the namespace is bound to: the binding is the
  authorisation (a ROS message carries no token), so a namespace bound by no service call
  changes nothing. ``camera_info`` is kept (the intrinsics of the frames that follow, and of
  a ``create_session`` that gives none); ``candidates`` replaces the pool; ``image``,
  ``depth`` and ``camera_pose`` make frames (:mod:`.assembler`).
* **Refusals** of topic messages (undecodable CDR, a bad field, an incomplete frame) are
  published as an ``agilegs_interfaces/msg/Status`` on ``<ns>/errors`` and, once bound, as
  the usual :class:`~agilegs.schemas.errors.ErrorBody` on ``agilegs/<session>/errors``;
  they change nothing.
* **Decisions** on a bound session (made over any transport) are published on
  ``<ns>/decision`` (PoseStamped) and ``<ns>/shortlist`` (PoseArray).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from agilegs.client.ros2 import FieldError, Namespace
from agilegs.client.ros2 import messages as m
from agilegs.client.ros2.frames import depth_to_array, image_to_rgb, intrinsics_of
from agilegs.client.ros2.keys import INPUT_TOPICS, SERVICES
from agilegs.schemas import PoolOut, SelectResponse, SessionInfo, codec, keys
from agilegs.schemas.errors import ErrorCode

from ...errors import ServiceError
from ..gateway import Gateway, Reply, Request
from ..requests import parse_request_id
from .assembler import Dropped, FrameAssembler
from .convert import (
    Binding,
    create_body,
    decision_msgs,
    frame_body,
    pool_body,
    pose_part,
    select_body,
    select_response_msg,
    status_msg,
)

__all__ = ["Ros2Adapter"]

log = logging.getLogger(__name__)

TRANSPORT = "ros2"

_PARTS_OF_FIELDS = (("depth", "depth"), ("pose", "camera_pose"), ("intrinsics", "camera_info"),
                    ("image", "image"))


def faulty_part(field: str | None, default: str) -> str:
    """The topic of the frame part a refused ``add_observations`` field belongs to (e.g.
    ``observations.0.depth.shape`` -> ``depth``, ``...pose.orientation_xyzw`` ->
    ``camera_pose``); ``default`` when the field names none."""
    names = (field or "").split(".")
    for name, topic in _PARTS_OF_FIELDS:
        if any(n == name or n.startswith(name + "_") for n in names):
            return topic
    return default
_STOP = object()


def _bearer(token: str) -> bytes | None:
    return b"Bearer " + token.strip().encode() if token.strip() else None


class _Space:
    """One served namespace: its binding, last camera info, frame assembler and worker."""

    def __init__(self, ns: Namespace) -> None:
        self.ns = ns
        self.binding: Binding | None = None
        self.camera: Any = None
        self.intrinsics: dict[str, Any] | None = None
        self.frames = FrameAssembler()
        self.inbox: queue.Queue[Any] = queue.Queue()
        self.worker: threading.Thread | None = None

    def bind(self, binding: Binding) -> None:
        if self.binding != binding:
            self.frames.clear()
        self.binding = binding
        self.frames.expect_depth = binding.expect_depth


class Ros2Adapter:
    """Serves agilegs' ROS 2 topics and services under ``namespaces`` over a Zenoh session
    (the server's) until :meth:`close`.

    Args:
        gateway: the request pipeline.
        namespaces: the namespaces served (fully qualified ROS names as the keys carry them:
            the bridge's namespace followed by the topics', e.g. ``/bot1/agilegs``).
    """

    def __init__(self, gateway: Gateway, namespaces: Sequence[str]) -> None:
        self.gateway = gateway
        self.spaces = {s.ns.prefix: s for s in (_Space(Namespace(n)) for n in namespaces)}
        if len(self.spaces) != len(namespaces):
            raise ValueError(f"ROS 2 namespaces repeat: {list(namespaces)}")
        self.session: Any = None
        self._declared: list[Any] = []
        self._closing = False
        self._poses: dict[int, dict[int, np.ndarray]] = {}

    # ------------------------------------------------------------------ lifecycle
    def start(self, zsession: Any) -> None:
        """Declare the subscribers and queryables on ``zsession`` and start the workers."""
        self.session = zsession
        m.typestore()  # build the type store now, not on the first message
        try:
            for space in self.spaces.values():
                for leaf in INPUT_TOPICS:
                    self._declared.append(zsession.declare_subscriber(
                        space.ns.key(leaf), _direct(self._on_sample(space, leaf))))
                for leaf in SERVICES:
                    self._declared.append(zsession.declare_queryable(
                        space.ns.key(leaf), _direct(self._on_query(space, leaf)),
                        complete=True))
        except Exception:
            self._undeclare()
            raise
        for space in self.spaces.values():
            space.worker = threading.Thread(target=self._drain, args=(space,), daemon=True,
                                            name=f"agilegs-ros2-{space.ns.prefix}")
            space.worker.start()
        self.gateway.decision_hooks.append(self.publish_decision)
        log.info("ros2: serving %s", ", ".join(s.ns.name for s in self.spaces.values()))

    def close(self) -> None:
        """Undeclare everything and stop the workers (the Zenoh session stays open)."""
        self._closing = True
        if self.publish_decision in self.gateway.decision_hooks:
            self.gateway.decision_hooks.remove(self.publish_decision)
        self._undeclare()
        for space in self.spaces.values():
            space.inbox.put(_STOP)
        for space in self.spaces.values():
            if space.worker is not None:
                space.worker.join(timeout=10)
        self.session = None

    def _undeclare(self) -> None:
        for entity in self._declared:
            try:
                entity.undeclare()
            except Exception:
                log.debug("ros2: undeclare failed", exc_info=True)
        self._declared.clear()

    # ------------------------------------------------------------------ arrival
    def _on_sample(self, space: _Space, leaf: str) -> Callable[[Any], None]:
        def on_sample(sample: Any) -> None:
            if not self._closing:
                space.inbox.put(("topic", leaf, sample.payload.to_bytes(),
                                 time.perf_counter()))
        return on_sample

    def _on_query(self, space: _Space, leaf: str) -> Callable[[Any], None]:
        def on_query(query: Any) -> None:
            if self._closing:
                query.drop()
                return
            space.inbox.put(("service", leaf, query, time.perf_counter()))
        return on_query

    def _drain(self, space: _Space) -> None:
        while True:
            try:
                item = space.inbox.get(timeout=1.0)
            except queue.Empty:  # frames that never complete are dropped past their deadline
                try:
                    self._report_dropped(space, space.frames.expire())
                except Exception:
                    log.exception("ros2: expiring frames on %s failed", space.ns.name)
                continue
            if item is _STOP:
                return
            kind, leaf, data, t0 = item
            try:
                if kind == "topic":
                    self._topic(space, leaf, data, t0)
                else:
                    self._service(space, leaf, data, t0)
            except Exception:  # a bug must not stop the namespace's worker
                log.exception("ros2: %s %s on %s failed", kind, leaf, space.ns.name)
                if kind == "service":
                    data.drop()

    # ------------------------------------------------------------------ topics
    def _topic(self, space: _Space, leaf: str, raw: bytes, t0: float) -> None:
        stamp = None
        try:
            self.gateway.check_size(len(raw))
            message = self._decode(raw, INPUT_TOPICS[leaf], leaf)
            stamp = message.header.stamp
            if leaf == "camera_info":
                space.intrinsics = intrinsics_of(message, "camera_info")
                space.camera = message
                return
            binding = self._bound(space)
            if leaf == "candidates":
                self._run(space, "set_pool", binding.session, pool_body(message, binding), t0,
                          leaf, stamp)
                return
            part = (image_to_rgb(message, "image") if leaf == "image" else
                    depth_to_array(message, "depth") if leaf == "depth" else
                    pose_part(message, binding))
            frames, dropped = space.frames.add(leaf, m.stamp_ns(stamp), part)
            self._report_dropped(space, dropped)
            for frame in frames:
                stamp = m.stamp_msg(frame.stamp_ns, ns=True)
                try:
                    body = frame_body(frame.image, frame.camera_pose, frame.depth,
                                      space.intrinsics)
                except FieldError as exc:
                    self._refuse(space, ServiceError(422, ErrorCode.INVALID, str(exc),
                                                     exc.field), "add_observations",
                                 faulty_part(exc.field, leaf), stamp)
                    continue
                self._run(space, "add_observations", binding.session, body, t0, leaf, stamp)
        except FieldError as exc:
            self._refuse(space, ServiceError(422, ErrorCode.INVALID, str(exc), exc.field),
                         _TOPIC_OPS[leaf], leaf, stamp)
        except ServiceError as err:
            self._refuse(space, err, _TOPIC_OPS[leaf], leaf, stamp)

    def _run(self, space: _Space, op: str, session: str, body: dict[str, Any], t0: float,
             topic: str, stamp: Any) -> None:
        reply = self._handle(op, session, body, t0, authenticated=True)
        if not reply.ok:
            assert reply.error is not None
            if op == "add_observations":  # the part at fault, not the one that completed it
                topic = faulty_part(reply.error.field, topic)
            self._publish_error(space, reply.error, topic, stamp, reply.body)

    def _report_dropped(self, space: _Space, dropped: list[Dropped]) -> None:
        """Report each incomplete frame given up, on the topic of the first part it lacked."""
        for d in dropped:
            self._refuse(space, ServiceError(
                422, ErrorCode.INVALID, f"the frame stamped {d.stamp_ns} ns was dropped "
                f"incomplete: no {' and no '.join(d.missing)} arrived for it",
                d.missing[0]), "add_observations", d.missing[0] if d.missing else "image",
                m.stamp_msg(d.stamp_ns, ns=True))

    def _refuse(self, space: _Space, err: ServiceError, op: str, topic: str,
                stamp: Any) -> None:
        """Count a refusal made here and publish it."""
        reply = self.gateway.error_reply(err, codec.MSGPACK, TRANSPORT, op)
        self._publish_error(space, err, topic, stamp, reply.body)

    def _publish_error(self, space: _Space, err: ServiceError, topic: str, stamp: Any,
                       body: bytes) -> None:
        session = space.binding.session if space.binding is not None else ""
        log.info("ros2: %s on %s refused: %s", topic, space.ns.name, err.message)
        self._put(space.ns.key("errors"), m.serialize(status_msg(
            err.status, err.code, err.message, err.field, session=session, topic=topic,
            stamp=stamp)), m_encoding=True)
        if session:
            self._put(keys.session_key(session, keys.ERRORS), body, m_encoding=False)

    # ------------------------------------------------------------------ services
    def _service(self, space: _Space, leaf: str, query: Any, t0: float) -> None:
        service = SERVICES[leaf]
        try:
            raw = query.payload.to_bytes() if query.payload is not None else b""
            try:
                self.gateway.check_size(len(raw))
                req = self._decode(raw, m.request_type(service), "request")
                self.gateway.authenticate(_bearer(req.token), "token")
                resp = {"create_session": self._create, "open_session": self._open,
                        "select": self._select}[leaf](space, req, t0)
            except FieldError as exc:
                err = ServiceError(422, ErrorCode.INVALID, str(exc), exc.field)
                resp = self._refusal(space, leaf, self.gateway.error_reply(
                    err, codec.MSGPACK, TRANSPORT, _SERVICE_OPS[leaf]))
            except ServiceError as err:
                resp = self._refusal(space, leaf, self.gateway.error_reply(
                    err, codec.MSGPACK, TRANSPORT, _SERVICE_OPS[leaf]))
            try:
                query.reply(query.key_expr, m.serialize(resp), encoding=_cdr())
            except Exception:
                log.debug("ros2: could not reply on %s", query.key_expr, exc_info=True)
        finally:
            query.drop()

    def _create(self, space: _Space, req: Any, t0: float) -> Any:
        body = create_body(req, space.camera)
        reply = self._handle("create_session", None, body, t0, authenticated=True,
                             request_id=_request_id(req))
        if not reply.ok:
            return self._refusal(space, "create_session", reply)
        assert isinstance(reply.model, SessionInfo)
        sid = reply.model.id
        space.bind(Binding.of(req, sid))
        return m.msg(m.response_type(m.CREATE_SESSION), status=self._status(reply, sid),
                     session=sid)

    def _open(self, space: _Space, req: Any, t0: float) -> Any:
        sid = req.session.strip()
        if not sid:
            raise FieldError("session", "name the session to open")
        reply = self._handle("get_session", sid, None, t0, authenticated=True)
        if not reply.ok:
            return self._refusal(space, "open_session", reply)
        info = reply.model
        assert isinstance(info, SessionInfo)
        space.bind(Binding.of(req, sid))
        return m.msg(m.response_type(m.OPEN_SESSION), status=self._status(reply, sid),
                     session=sid, num_views=info.num_views, pool_size=info.pool_size,
                     version=info.version)

    def _select(self, space: _Space, req: Any, t0: float) -> Any:
        binding = self._bound(space)
        reply = self._handle("select", binding.session, select_body(req, binding), t0,
                             authenticated=True, request_id=_request_id(req))
        if not reply.ok:
            return self._refusal(space, "select", reply)
        resp = reply.model
        assert isinstance(resp, SelectResponse)
        poses = self._poses.pop(id(resp), None)
        if poses is None:
            poses = self._pool_poses(binding.session)
        return select_response_msg(resp, self._status(reply, binding.session), poses, binding)

    def _refusal(self, space: _Space, leaf: str, reply: Reply) -> Any:
        """The service's response carrying only the refusal in ``reply``."""
        session = space.binding.session if space.binding is not None else ""
        status = self._status(reply, session, leaf)
        if leaf == "select":
            return select_response_msg(None, status, {}, space.binding)
        if leaf == "create_session":
            return m.msg(m.response_type(m.CREATE_SESSION), status=status, session="")
        return m.msg(m.response_type(m.OPEN_SESSION), status=status, session="", num_views=0,
                     pool_size=0, version=0)

    @staticmethod
    def _status(reply: Reply, session: str, topic: str = "") -> Any:
        err = reply.error
        if err is None:
            return status_msg(session=session, topic=topic)
        return status_msg(err.status, err.code, err.message, err.field, session=session,
                          topic=topic, retry_after=err.retry_after)

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _decode(raw: bytes, typename: str, what: str) -> Any:
        try:
            return m.deserialize(raw, typename)
        except m.CdrError as exc:
            raise ServiceError(400, ErrorCode.BAD_REQUEST, f"{what}: {exc}",
                               f"{what}.payload") from None

    @staticmethod
    def _bound(space: _Space) -> Binding:
        if space.binding is None:
            raise ServiceError(404, ErrorCode.NOT_FOUND,
                               f"namespace {space.ns.name} is bound to no session: call "
                               f"{space.ns.name}/create_session or "
                               f"{space.ns.name}/open_session first", "namespace")
        return space.binding

    def _handle(self, op: str, session: str | None, body: dict[str, Any] | None, t0: float,
                *, authenticated: bool, request_id: str | None = None) -> Reply:
        return self.gateway.handle(Request(
            op=op, session=session, body=codec.dump(body, codec.MSGPACK) if body is not None
            else None, content_type=codec.MSGPACK, accept=codec.MSGPACK, transport=TRANSPORT,
            t0=t0, authenticated=authenticated, request_id=request_id))

    def _pool_poses(self, session: str) -> dict[int, np.ndarray]:
        try:
            pool = self.gateway.dispatch("get_pool", session, None)
        except ServiceError:
            return {}
        assert isinstance(pool, PoolOut)
        return {c.id: c.pose.to_matrix() for c in pool.candidates}

    def _put(self, key: str, payload: bytes, *, m_encoding: bool) -> None:
        if self.session is None:
            return
        try:
            self.session.put(key, payload, encoding=_cdr() if m_encoding else codec.MSGPACK)
        except Exception:
            log.debug("ros2: could not publish on %s", key, exc_info=True)

    # ------------------------------------------------------------------ decisions
    def publish_decision(self, session: str, resp: SelectResponse) -> None:
        """Publish a decision on every namespace bound to ``session`` (a gateway hook)."""
        bound = [s for s in self.spaces.values()
                 if s.binding is not None and s.binding.session == session]
        if not bound or self._closing:
            return
        poses = self._pool_poses(session)
        self._poses = {id(resp): poses}  # the Select reply of this decision reuses them
        for space in bound:
            assert space.binding is not None
            chosen, shortlist = decision_msgs(resp, poses, space.binding)
            self._put(space.ns.key("decision"), m.serialize(chosen), m_encoding=True)
            self._put(space.ns.key("shortlist"), m.serialize(shortlist), m_encoding=True)


_TOPIC_OPS = {"camera_info": "camera_info", "candidates": "set_pool",
              "image": "add_observations", "depth": "add_observations",
              "camera_pose": "add_observations"}
"""The operation a refused topic message is counted under."""
_SERVICE_OPS = {"create_session": "create_session", "open_session": "get_session",
                "select": "select"}


def _direct(callback: Callable[[Any], None]) -> Any:
    """``callback`` run on Zenoh's receiving thread, in the order the messages came (a plain
    Python callback gets a thread of its own per subscriber or queryable, and the order
    across them is lost); it only queues the message."""
    import zenoh

    try:
        return zenoh.handlers.Callback(callback, indirect=False)
    except TypeError:  # a zenoh without the option
        return callback


def _cdr() -> Any:
    import zenoh

    return zenoh.Encoding.APPLICATION_CDR


def _request_id(req: Any) -> str | None:
    """The ``request_id`` of a service request ("" : none; 400 naming it when malformed)."""
    text = str(req.request_id).strip()
    return parse_request_id(text, "request_id") if text else None

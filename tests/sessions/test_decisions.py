"""The decisions feed: the log's numbering, bound, waits and closing (unit), and the
``get_decisions`` operation over HTTP in process: long poll, event stream, token, deletion."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from typing import Any

import msgpack
import pytest
from conftest import SMALL_INTRINSICS, InProcess, ring_poses

from agilegs.client import AuthenticationError, NotFoundError, ValidationError
from agilegs.schemas import Candidate, Pose, SelectResponse, codec
from agilegs.service.sessions.decisions import DecisionLog
from agilegs.service.transports.gateway import Request

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}
TOKEN = "feed-token"


def fake(session: str, cid: int) -> SelectResponse:
    return SelectResponse.model_construct(
        session=session, method="random", chosen=Candidate(id=cid, pose=Pose(matrix=[
            [1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])),
        shortlist=[], anchor=None, scores=[], eligible=[cid], psi_trace=[],
        latency_ms={"total": 1.0}, core_ms=1.0, server_ms=None, committed=None, version=1,
        time=0.0)


def make(api: InProcess, sid: str = "s", pool: int = 10, **kwargs: Any) -> None:
    with api.client(**kwargs) as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=60,
                         pool=ring_poses(pool), defaults={"method": "random"})


def events(text: str) -> list[dict[str, Any]]:
    """The server-sent events of a stream's text: [{"event", "id", "data"}]."""
    out = []
    for block in text.split("\n\n"):
        ev: dict[str, Any] = {}
        for line in block.splitlines():
            if line.startswith(":"):
                continue
            name, _, value = line.partition(": ")
            ev[name] = json.loads(value) if name == "data" else value
        if ev:
            out.append(ev)
    return out


# ============================================================================ the log
def test_the_log_numbers_in_order_and_reads_each_decision_once() -> None:
    log = DecisionLog(capacity=100)
    for i in range(7):
        log.record("a", fake("a", i))
        assert log.read("a", i).last_seq == i + 1
    log.record("b", fake("b", 99))
    seen: list[int] = []
    after = 0
    while True:  # small pages: every decision once, in order
        out = log.read("a", after, limit=3)
        if not out.decisions:
            break
        seen += [e.seq for e in out.decisions]
        assert [e.decision.chosen.id for e in out.decisions] == [s - 1 for s in
                                                                 [e.seq for e in out.decisions]]
        after = out.next_after
    assert seen == list(range(1, 8))
    assert log.read("a", 7).next_after == 7 and log.read("a", 7).missed == 0
    assert [e.seq for e in log.read("b").decisions] == [1]  # per session
    assert log.read("a").epoch != log.read("b").epoch


def test_past_its_bound_the_log_says_how_many_were_missed() -> None:
    log = DecisionLog(capacity=3)
    for i in range(5):
        log.record("a", fake("a", i))
    out = log.read("a", 0)
    assert [e.seq for e in out.decisions] == [3, 4, 5] and out.missed == 2
    assert log.read("a", 1).missed == 1 and log.read("a", 2).missed == 0
    assert log.read("a", 4).missed == 0 and [e.seq for e in log.read("a", 4).decisions] == [5]


def test_a_read_waits_for_the_next_decision_and_no_longer_than_asked() -> None:
    log = DecisionLog()
    log.record("a", fake("a", 0))
    threading.Timer(0.3, log.record, ("a", fake("a", 1))).start()
    t0 = time.monotonic()
    out = log.read("a", 1, wait=10)
    assert [e.seq for e in out.decisions] == [2] and time.monotonic() - t0 < 5
    t0 = time.monotonic()
    assert log.read("a", 2, wait=0.3).decisions == []
    assert 0.25 < time.monotonic() - t0 < 3
    # an after from another epoch (beyond the last) answers at once
    t0 = time.monotonic()
    out = log.read("a", 50, wait=5)
    assert out.decisions == [] and out.next_after == 2 and time.monotonic() - t0 < 1


def test_at_most_max_waiters_reads_block_at_once() -> None:
    log = DecisionLog(max_waiters=1)
    log.record("a", fake("a", 0))
    done: list[float] = []
    first = threading.Thread(target=lambda: done.append(len(log.read("a", 1, wait=5).decisions)))
    first.start()
    time.sleep(0.2)
    t0 = time.monotonic()
    assert log.read("a", 1, wait=5).decisions == []  # the second does not wait
    assert time.monotonic() - t0 < 1
    log.record("a", fake("a", 1))
    first.join(5)
    assert done == [1]


def test_closing_wakes_the_readers_and_keeps_what_they_had_not_read() -> None:
    log = DecisionLog()
    log.record("a", fake("a", 0))
    got: list[Any] = []
    t = threading.Thread(target=lambda: got.append(log.read("a", 1, wait=10)))
    t.start()
    time.sleep(0.2)
    log.record("a", fake("a", 1))  # wakes the reader with seq 2
    t.join(5)
    assert [e.seq for e in got[0].decisions] == [2] and not got[0].closed
    log.record("a", fake("a", 2))
    t = threading.Thread(target=lambda: got.append(log.read("a", 3, wait=10)))
    t.start()
    time.sleep(0.2)
    t0 = time.monotonic()
    log.close("a")
    t.join(5)
    assert got[1].closed and got[1].decisions == [] and time.monotonic() - t0 < 2
    log.open("a")  # created again: a new epoch from 1
    out = log.read("a")
    assert out.epoch != got[1].epoch and out.last_seq == 0 and not out.closed


def test_shutdown_wakes_blocking_and_async_waiters() -> None:
    log = DecisionLog()
    got: list[Any] = []
    t = threading.Thread(target=lambda: got.append(log.read("a", 0, wait=30)))
    t.start()

    async def wait() -> float:
        t0 = time.monotonic()
        await log.wait_async("a", 0, 30)
        return time.monotonic() - t0

    async def both() -> float:
        task = asyncio.ensure_future(wait())
        await asyncio.sleep(0.2)
        await asyncio.get_running_loop().run_in_executor(None, log.shutdown)
        return await task

    assert asyncio.run(both()) < 5
    t.join(5)
    assert not t.is_alive() and got[0].decisions == []


# ============================================================================ over HTTP
def test_polls_get_every_decision_once_in_order(api: InProcess) -> None:
    make(api)
    with api.client() as c:
        made = [c.select("s", commit=i % 2 == 0, seed=i) for i in range(5)]
        got: list[Any] = []
        after = 0
        for _ in range(10):
            out = c.get_decisions("s", after=after, limit=2)
            got += out.decisions
            after = out.next_after
            if not out.decisions:
                break
        assert [e.seq for e in got] == [1, 2, 3, 4, 5]
        for e, d in zip(got, made, strict=True):
            assert e.decision.model_dump() == d.model_dump()  # server_ms included
        assert got[0].decision.committed is not None and got[1].decision.committed is None
        assert out.last_seq == 5 and out.missed == 0 and not out.closed


def test_a_long_poll_returns_with_the_next_decision_and_holds_no_worker(api: InProcess) -> None:
    make(api)
    workers = api.server.settings.workers
    with api.client() as c:
        c.select("s")
        results: list[Any] = []
        pollers = [threading.Thread(target=lambda: results.append(
            c.get_decisions("s", after=1, wait=20))) for _ in range(workers + 2)]
        for p in pollers:
            p.start()
        time.sleep(0.5)
        t0 = time.monotonic()
        d = c.select("s", seed=7)  # more polls wait than there are workers: it still runs
        for p in pollers:
            p.join(20)
        assert time.monotonic() - t0 < 10
        assert len(results) == workers + 2
        for out in results:
            assert [e.seq for e in out.decisions] == [2]
            assert out.decisions[0].decision.chosen.id == d.chosen.id


def test_the_wait_is_bounded_and_its_fields_are_checked(api_factory: Any) -> None:
    api = api_factory(max_poll_wait=0.3)
    make(api)
    with api.client() as c, api.http() as h:
        t0 = time.monotonic()
        out = c.get_decisions("s", wait=30)
        assert out.decisions == [] and time.monotonic() - t0 < 3
        for params, field in [({"wait": "61"}, "query.wait"), ({"after": "-1"}, "query.after"),
                              ({"limit": "0"}, "query.limit"), ({"since": "1"}, "query.since")]:
            r = h.get("/v1/sessions/s/decisions", params=params)
            assert r.status_code == 422 and r.json()["error"]["field"] == field, r.text
        with pytest.raises(ValidationError):
            c.get_decisions("s", wait=-1)
        with pytest.raises(NotFoundError):
            c.get_decisions("nope")
        # msgpack answers, as for every operation
        r = h.get("/v1/sessions/s/decisions", headers={"accept": codec.MSGPACK})
        assert r.headers["content-type"] == codec.MSGPACK
        assert msgpack.unpackb(r.content)["session"] == "s"


def test_the_feed_through_the_gateway_as_zenoh_sends_it(api: InProcess) -> None:
    # a msgpack body and a blocking wait in the handler (Zenoh queries, forwarded requests)
    make(api)
    gw = api.server.gateway
    with api.client() as c:
        c.select("s")
        threading.Timer(0.3, lambda: c.select("s", seed=3)).start()
        t0 = time.monotonic()
        reply = gw.handle(Request(op="get_decisions", session="s", transport="zenoh",
                                  body=msgpack.packb({"after": 1, "wait": 10}),
                                  content_type=codec.MSGPACK, accept=codec.MSGPACK))
        assert reply.ok and time.monotonic() - t0 < 8
        out = msgpack.unpackb(reply.body)
        assert [e["seq"] for e in out["decisions"]] == [2]
        bad = gw.handle(Request(op="get_decisions", session="s", transport="zenoh",
                                body=msgpack.packb({"after": "x"}), content_type=codec.MSGPACK,
                                accept=codec.MSGPACK))
        assert bad.status == 422 and bad.error is not None and bad.error.field == "body.after"
        empty = gw.handle(Request(op="get_decisions", session="s", transport="zenoh", body=b"",
                                  content_type=codec.MSGPACK, accept=codec.MSGPACK))
        assert empty.ok and msgpack.unpackb(empty.body)["last_seq"] == 2


def test_deleting_the_session_closes_waiting_polls_and_streams(api: InProcess) -> None:
    make(api)
    with api.client() as c, api.http() as h:
        c.select("s")
        got: dict[str, Any] = {}

        def poll() -> None:
            got["poll"] = c.get_decisions("s", after=1, wait=20)

        def stream() -> None:
            got["stream"] = h.get("/v1/sessions/s/decisions", params={"wait": "20"},
                                  headers={"accept": "text/event-stream"})

        threads = [threading.Thread(target=poll), threading.Thread(target=stream)]
        for t in threads:
            t.start()
        time.sleep(0.5)
        t0 = time.monotonic()
        c.delete_session("s")
        for t in threads:
            t.join(15)
        assert time.monotonic() - t0 < 10
        assert got["poll"].closed and got["poll"].decisions == []
        evs = events(got["stream"].text)
        assert [e["event"] for e in evs] == ["feed", "decision", "closed"]
        assert evs[1]["data"]["seq"] == 1
        with pytest.raises(NotFoundError):  # the feed is gone with the session
            c.get_decisions("s", after=1)
        with pytest.raises(NotFoundError):
            c.get_session("s")
        make(api, "t")
        c.select("t")
        first = c.get_decisions("t").epoch
        c.delete_session("t")
        make(api, "t")  # created again: another epoch, numbered from 1
        c.select("t")
        again = c.get_decisions("t")
        assert again.epoch != first and [e.seq for e in again.decisions] == [1]


def test_the_event_stream_sends_each_decision_once_and_resumes(api: InProcess) -> None:
    make(api)
    with api.client() as c, api.http() as h:
        made = [c.select("s", seed=i) for i in range(3)]
        threading.Timer(0.4, lambda: made.append(c.select("s", seed=9))).start()
        r = h.get("/v1/sessions/s/decisions", params={"wait": "1.5"},
                  headers={"accept": "text/event-stream"})
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        evs = events(r.text)
        assert evs[0]["event"] == "feed" and evs[0]["data"]["last_seq"] == 3
        epoch = evs[0]["data"]["epoch"]
        decisions = [e for e in evs if e["event"] == "decision"]
        assert [e["data"]["seq"] for e in decisions] == [1, 2, 3, 4]
        assert [e["id"] for e in decisions] == [f"{epoch}:{i}" for i in (1, 2, 3, 4)]
        assert [e["data"]["decision"]["chosen"]["id"] for e in decisions] == [
            d.chosen.id for d in made]
        # an EventSource reconnecting with Last-Event-ID goes on after it
        r = h.get("/v1/sessions/s/decisions", params={"wait": "0"},
                  headers={"accept": "text/event-stream", "last-event-id": f"{epoch}:2"})
        assert [e["data"]["seq"] for e in events(r.text) if e["event"] == "decision"] == [3, 4]
        # ... and from the start when the id comes from another epoch (a restart)
        r = h.get("/v1/sessions/s/decisions", params={"wait": "0"},
                  headers={"accept": "text/event-stream", "last-event-id": "old-1:3"})
        assert [e["data"]["seq"] for e in events(r.text)
                if e["event"] == "decision"] == [1, 2, 3, 4]
        # refusals before the stream are the usual error bodies
        r = h.get("/v1/sessions/s/decisions", params={"limit": "x"},
                  headers={"accept": "text/event-stream"})
        assert r.status_code == 422 and r.json()["error"]["field"] == "query.limit"


def test_the_feed_needs_the_token(api_factory: Any) -> None:
    api = api_factory(token=TOKEN)
    make(api, token=TOKEN)
    with api.client(token=TOKEN) as c, api.http() as h:
        c.select("s")
        with pytest.raises(AuthenticationError):
            api.client().get_decisions("s")
        r = h.get("/v1/sessions/s/decisions", headers={"accept": "text/event-stream"})
        assert r.status_code == 401
        assert [e.seq for e in c.get_decisions("s", wait=1).decisions] == [1]
        r = h.get("/v1/sessions/s/decisions", params={"wait": "0"}, headers={
            "accept": "text/event-stream", "authorization": f"Bearer {TOKEN}"})
        assert [e["event"] for e in events(r.text)] == ["feed", "decision"]


def test_the_stream_says_what_it_missed_and_keeps_alive(api_factory: Any,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    from agilegs.service.transports.http import decisions as http_decisions

    monkeypatch.setattr(http_decisions, "HEARTBEAT_S", 0.3)
    api = api_factory(decision_log=2)
    make(api)
    with api.client() as c, api.http() as h:
        for i in range(4):
            c.select("s", seed=i)
        r = h.get("/v1/sessions/s/decisions", params={"wait": "1"},
                  headers={"accept": "text/event-stream"})
        evs = events(r.text)
        assert [e["event"] for e in evs] == ["feed", "missed", "decision", "decision"]
        assert evs[1]["data"] == {"missed": 2, "after": 0}
        assert [e["data"]["seq"] for e in evs[2:]] == [3, 4]
        assert ": keep-alive" in r.text  # a second of silence, heartbeats every 0.3 s

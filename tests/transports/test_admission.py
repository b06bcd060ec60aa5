"""Bounded memory and compute per request, fair queueing (in-process server, small limits):
bodies refused before parsing, images priced from their headers, the per-session queue,
deadlines and cancellation at stage boundaries, the select cost estimate, /readyz."""

from __future__ import annotations

import base64
import io
import json
import os
import threading
import time
import uuid
from typing import Any

import msgpack
import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, InProcess, ring_poses
from PIL import Image

from agilegs import schemas as m
from agilegs.schemas import codec
from agilegs.schemas.errors import ErrorCode
from agilegs.service.errors import ServiceError
from agilegs.service.nbv import cancel
from agilegs.service.settings import Settings
from agilegs.service.transports.admission import (
    Admission,
    Ticket,
    count_values,
    decoded_bytes,
    image_size,
)

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


def new_id() -> str:
    return f"t-{uuid.uuid4().hex[:8]}"


def _values(obj: Any) -> int:
    """The values of decoded data, counted plainly (the reference)."""
    if isinstance(obj, dict):
        return 1 + sum(_values(k) + _values(v) for k, v in obj.items())
    if isinstance(obj, list):
        return 1 + sum(_values(v) for v in obj)
    return 1


def _random_data(rng: np.random.Generator, depth: int = 0) -> Any:
    kind = rng.integers(0, 9 if depth < 4 else 7)
    if kind == 0:
        return int(rng.integers(-(2**40), 2**40))
    if kind == 1:
        return int(rng.integers(-40, 200))
    if kind == 2:
        return float(rng.normal())
    if kind == 3:
        return "x" * int(rng.integers(0, 300))
    if kind == 4:
        return bytes(int(rng.integers(0, 70000)) if rng.random() < 0.05 else 5)
    if kind == 5:
        return None if rng.random() < 0.5 else bool(rng.random() < 0.5)
    if kind == 6:
        return -float(rng.integers(0, 10))
    if kind == 7:
        return [_random_data(rng, depth + 1) for _ in range(int(rng.integers(0, 40)))]
    return {f"k{i}": _random_data(rng, depth + 1) for i in range(int(rng.integers(0, 20)))}


def test_msgpack_value_count_matches_the_decoded_data() -> None:
    from agilegs.service.transports.admission import _msgpack_values

    rng = np.random.default_rng(0)
    for _ in range(60):
        data = _random_data(rng)
        body = msgpack.packb(data, use_bin_type=True)
        want = _values(data)
        assert _msgpack_values(body, 10**9) == want
        assert _msgpack_values(body, want // 2) == want // 2 + 1  # stops past the limit
    # containers with 16- and 32-bit lengths, every integer width
    data = {"a": list(range(70000)), "b": [2**k for k in range(63)] + [-(2**k) for k in range(63)]}
    body = msgpack.packb(data)
    assert _msgpack_values(body, 10**9) == _values(data)


def test_bodies_with_too_many_values_are_refused_before_parsing() -> None:
    many = [[] for _ in range(50_000)]
    for kind, body in ((codec.JSON, json.dumps({"poses": many}).encode()),
                       (codec.MSGPACK, msgpack.packb({"poses": many}))):
        with pytest.raises(ServiceError) as exc:
            count_values(body, kind, 10_000)
        assert exc.value.status == 413 and exc.value.limit == "max_body_items"
        count_values(body, kind, 110_000)  # within the limit (JSON: counted at most twice)
    # a large body of few values (binary arrays, base64 in JSON) passes
    blob = bytes(3_000_000)
    count_values(msgpack.packb({"data": blob}), codec.MSGPACK, 1000)
    count_values(json.dumps({"data": base64.b64encode(blob).decode()}).encode(), codec.JSON,
                 1000)


def _png(w: int, h: int, mode: str = "RGB") -> bytes:
    buf = io.BytesIO()
    Image.new(mode, (w, h)).save(buf, format="PNG")
    return buf.getvalue()


def test_image_sizes_come_from_the_headers() -> None:
    for mode, px in (("RGB", 3), ("RGBA", 4), ("L", 1), ("I;16", 2)):
        img = m.ImageData(encoding="png", data=_png(40, 30, mode))
        assert image_size(img) == (40, 30, px)
        # the estimate covers what decoding really holds: Pillow's buffer, the RGB array
        obs = m.ObservationIn(pose={"matrix": np.eye(4).tolist()}, image=img)
        decoded = img.to_numpy()
        assert decoded_bytes(obs) >= decoded.nbytes + 40 * 30 * px
    raw = m.ImageData.from_numpy(np.zeros((8, 6, 3), np.float32))
    assert image_size(raw) == (6, 8, 12)
    assert image_size(m.ImageData(encoding="png", data=b"not a png")) == (0, 0, 0)


def test_admission_counts_and_refuses() -> None:
    adm = Admission(Settings(max_session_queue=2, max_queued=3, workers=1,
                             max_request_decoded_bytes=2 << 20,
                             max_inflight_decoded_bytes=3 << 20))
    adm.enter("select", "a")
    adm.enter("commit", "a")
    with pytest.raises(ServiceError) as exc:
        adm.enter("select", "a")
    assert exc.value.status == 429 and exc.value.retry_after and (
        exc.value.limit == "max_session_queue")
    adm.enter("get_session", "a")  # reads are never queued
    adm.enter("select", "b")
    with pytest.raises(ServiceError) as exc:
        adm.enter("select", "c")
    assert exc.value.status == 503 and exc.value.limit == "max_queued"
    assert adm.saturation() is not None
    for op, sid in (("select", "a"), ("commit", "a"), ("select", "b")):
        adm.leave(op, sid)
    assert adm.compute == 0 and adm.saturation() is None
    with pytest.raises(ServiceError) as exc, adm.decoded(3 << 20):
        pass
    assert exc.value.status == 413 and exc.value.limit == "max_request_decoded_bytes"
    with adm.decoded(2 << 20):
        with pytest.raises(ServiceError) as exc, adm.decoded(2 << 20):
            pass
        assert exc.value.status == 503 and exc.value.limit == "max_inflight_decoded_bytes"
    assert adm.inflight_bytes == 0


def test_a_ticket_cancels_at_the_next_checkpoint() -> None:
    t = Ticket(time.monotonic() + 60)
    with cancel.scope(t.check):
        cancel.checkpoint()
        t.cancel("the client disconnected")
        with pytest.raises(ServiceError) as exc:
            cancel.checkpoint()
    assert exc.value.status == 504 and exc.value.code == ErrorCode.DEADLINE_EXCEEDED
    cancel.checkpoint()  # outside the scope: nothing
    with pytest.raises(ServiceError):
        Ticket(time.monotonic() - 1).check()


# ---------------------------------------------------------------------- through the server
def _state(api: InProcess, sid: str) -> tuple:
    with api.client() as c:
        s = c.get_session(sid)
        return (s.version, s.num_views, s.pool_size, s.information.digest,
                [v.id for v in c.list_views(sid).views])


def _session(api: InProcess, n: int = 200, pool: int = 12, **kw: Any) -> str:
    sid = new_id()
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=n,
                         pool=ring_poses(pool), **kw)
    return sid


def test_images_over_the_request_budget_are_refused_before_decoding(api_factory: Any) -> None:
    api = api_factory(max_request_decoded_bytes=1 << 20)
    sid = _session(api)
    before = _state(api, sid)
    intr = {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240}
    obs = [{"pose": {"matrix": p.tolist()}, "intrinsics": intr,
            "image": {"encoding": "png", "data": base64.b64encode(_png(320, 240)).decode()}}
           for p in ring_poses(3)]
    with api.http(timeout=30) as h:
        r = h.post(f"/v1/sessions/{sid}/observations", json={"observations": obs})
        assert r.status_code == 413, r.text
        err = r.json()["error"]
        assert err["limit"] == "max_request_decoded_bytes" and "max_request_decoded_bytes" in (
            err["message"])
        assert _state(api, sid) == before
        r = h.post(f"/v1/sessions/{sid}/observations", json={"observations": obs[:1]})
        assert r.status_code == 200, r.text  # one frame fits
    assert api.server.gateway.admission.inflight_bytes == 0


def test_a_pool_of_millions_of_items_is_refused_early(api_factory: Any) -> None:
    api = api_factory(max_body_items=10_000)
    sid = _session(api)
    before = _state(api, sid)
    with api.http(timeout=30) as h:
        for kind, body in ((codec.JSON, b'{"poses": [' + b",".join([b"[]"] * 20_000) + b"]}"),
                           (codec.MSGPACK, msgpack.packb({"poses": [[]] * 20_000}))):
            r = h.put(f"/v1/sessions/{sid}/pool", content=body,
                      headers={"content-type": kind, "accept": codec.JSON})
            assert r.status_code == 413 and r.json()["error"]["limit"] == "max_body_items"
    assert _state(api, sid) == before


def test_an_empty_raw_upload_is_422(api: InProcess) -> None:
    sid = _session(api)
    with api.http(timeout=30) as h:
        r = h.put(f"/v1/sessions/{sid}/gaussians", content=b"",
                  headers={"content-type": "application/octet-stream"})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["field"] == "body" and "empty" in r.json()["error"]["message"]


def test_a_select_over_the_cost_limit_is_refused_with_its_estimate(api_factory: Any) -> None:
    api = api_factory(max_select_seconds=1.0)
    sid = _session(api, n=2000, pool=400)
    before = _state(api, sid)
    with api.http(timeout=30) as h:
        r = h.post(f"/v1/sessions/{sid}/select", json={"method": "fisherrf", "commit": True})
        assert r.status_code == 422, r.text
        err = r.json()["error"]
        assert err["code"] == "limit_exceeded" and err["limit"] == "max_select_seconds"
        assert err["estimate"]["seconds"] > 1.0 and err["estimate"]["peak_bytes"] > 0
        assert err["field"] == "body.method"
        assert _state(api, sid) == before
        r = h.post(f"/v1/sessions/{sid}/select", json={"method": "random"})
        assert r.status_code == 200  # a cheap one goes through


def test_the_cost_limit_compares_the_time_bound_and_learns_the_machine(
        api_factory: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    from agilegs.service.nbv.budget import TIME_MARGIN, SpeedCalibration
    from agilegs.service.sessions import selection

    speed = SpeedCalibration()
    monkeypatch.setattr(selection, "SPEED", speed)
    probe = api_factory(max_select_seconds=1e6)
    sid = _session(probe, n=2000, pool=120)
    rec = probe.server.registry.session(sid).record
    cfg = selection.resolve_config(rec.defaults, m.SelectRequest(method="full_eig"), {})
    raw = selection.select_estimate(rec, "full_eig", cfg).seconds
    # a limit between the raw estimate and its bound: refused, the error carries the bound
    api = api_factory(max_select_seconds=raw * (1 + TIME_MARGIN) / 2)
    sid = _session(api, n=2000, pool=120)
    with api.http(timeout=60) as h:
        r = h.post(f"/v1/sessions/{sid}/select", json={"method": "full_eig"})
        assert r.status_code == 422, r.text
        err = r.json()["error"]
        assert err["limit"] == "max_select_seconds"
        assert err["estimate"]["seconds"] == pytest.approx(raw * TIME_MARGIN, rel=1e-6)
    # a select that ran slower than its estimate raises the factor, and so the bound
    with probe.http(timeout=120) as h:
        r = h.post(f"/v1/sessions/{sid}/select", json={"method": "random"})
        r = h.post(f"/v1/sessions/{_session(probe, n=2000, pool=120)}/select",
                   json={"method": "full_eig"})
        assert r.status_code == 200, r.text
    assert speed.samples == 1  # the full_eig select was timed (random's estimate is too short)
    for _ in range(3):
        speed.observe(1.0, 50.0)
    assert speed.factor >= 50.0
    with api.http(timeout=60) as h:
        r = h.post(f"/v1/sessions/{sid}/select", json={"method": "full_eig"})
        assert r.status_code == 422
        assert r.json()["error"]["estimate"]["seconds"] >= raw * 50.0 * TIME_MARGIN * (1 - 1e-6)


def test_deadlines_cancel_at_stage_boundaries(api_factory: Any) -> None:
    api = api_factory(max_select_seconds=1e6)
    sid = _session(api, n=1000, pool=400)
    before = _state(api, sid)
    with api.http(timeout=60) as h:
        r = h.post(f"/v1/sessions/{sid}/select", json={"method": "random", "commit": True},
                   headers={"x-deadline-ms": "0"})
        assert r.status_code == 504 and r.json()["error"]["code"] == "deadline_exceeded"
        assert h.post(f"/v1/sessions/{sid}/select", json={"method": "random"},
                      headers={"x-deadline-ms": "soon"}).status_code == 400
        # inside the computation: between two candidates of a full EIG over 400
        t0 = time.perf_counter()
        r = h.post(f"/v1/sessions/{sid}/select", json={"method": "full_eig", "commit": True},
                   headers={"x-deadline-ms": "300"})
        took = time.perf_counter() - t0
        assert r.status_code == 504, r.text
        assert took < 3.0
    assert _state(api, sid) == before
    assert api.server.gateway.admission.compute == 0


def test_reads_and_other_sessions_never_wait_behind_a_held_session(api_factory: Any) -> None:
    """Two changes wait for a session's lock (a long change holds it): its reads, and the
    other session's select, answer at once; a third change is refused (429); the waiting
    changes give up at their deadline."""
    api = api_factory(max_session_queue=2, workers=2, read_workers=2)
    busy, other = _session(api), _session(api)
    session = api.server.registry.session(busy)
    replies: list[int] = []
    with session.lock:  # a long change holds the session
        def waiter() -> None:
            with api.http(timeout=30) as h:
                replies.append(h.post(f"/v1/sessions/{busy}/views", json={"candidate_id": 0},
                                      headers={"x-deadline-ms": "1500"}).status_code)

        threads = [threading.Thread(target=waiter) for _ in range(2)]
        for t in threads:
            t.start()
        time.sleep(0.3)
        with api.http(timeout=30) as h:
            t0 = time.perf_counter()
            assert h.get(f"/v1/sessions/{busy}").status_code == 200  # its own read
            assert h.get(f"/v1/sessions/{busy}/views").status_code == 200
            r = h.post(f"/v1/sessions/{busy}/select", json={"method": "random"},
                       headers={"x-deadline-ms": "1000"})
            assert r.status_code == 429 and r.headers["retry-after"] == "1"
            assert r.json()["error"]["limit"] == "max_session_queue"
            assert h.post(f"/v1/sessions/{other}/select", json={"method": "random"}
                          ).status_code == 200
            assert time.perf_counter() - t0 < 1.0
            # one busy session holds one compute worker and leaves the server ready
            assert h.get("/readyz").json() == {"ready": True}
            assert api.server.gateway.admission.running == 1
        for t in threads:
            t.join()
    assert replies == [504, 504]  # gave up waiting for the lock at their deadline
    # the second, admitted behind the first, ran on a lower-priority thread
    bg = [t for t in threading.enumerate() if t.name.startswith("agilegs-bg")]
    assert bg, [t.name for t in threading.enumerate()]
    if hasattr(os, "getpriority"):
        base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        assert os.getpriority(os.PRIO_PROCESS, bg[0].native_id) >= min(base + 10, 19)
    with api.http(timeout=30) as h:
        assert h.get("/readyz").json() == {"ready": True}
    assert session.lock.acquire(timeout=1)
    session.lock.release()


def test_a_short_deadline_stops_every_method(api_factory: Any) -> None:
    """A 20 ms deadline answers 504 for every method that takes longer (the anchor checks it
    between its stages and ascent steps, scoring between candidates); nothing is committed.
    (AGILE-GS with warm kernels can select on this map within 50 ms.)"""
    api = api_factory(max_select_seconds=1e6)
    sid = _session(api, n=3000, pool=200)
    before = _state(api, sid)
    with api.http(timeout=60) as h:
        for method in ("fisherrf", "cover", "full_eig", "agile", "agile_plus"):
            r = h.post(f"/v1/sessions/{sid}/select", json={"method": method, "commit": True},
                       headers={"x-deadline-ms": "20"})
            assert r.status_code == 504, (method, r.text)
            assert r.json()["error"]["code"] == "deadline_exceeded"
    assert _state(api, sid) == before

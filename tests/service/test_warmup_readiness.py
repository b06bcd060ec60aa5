"""A server warms its kernels up in the background at start: ``/readyz`` answers 503 naming
the warm-up until it is done, and the server serves meanwhile."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from inprocess import serve_in_process

import agilegs.service.nbv.warmup as warmup


def test_readyz_waits_for_the_warm_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    release, called = threading.Event(), threading.Event()

    def slow_warm_up() -> dict[str, float]:
        called.set()
        assert release.wait(30)
        return {"total": 0.0}

    monkeypatch.setattr(warmup, "warm_up", slow_warm_up)
    with serve_in_process(tmp_path / "state", warmup=True) as srv, srv.http() as h:
        assert called.wait(30)
        r = h.get("/readyz")
        assert r.status_code == 503 and r.json() == {
            "ready": False, "reason": "compiling the selection kernels (warm-up: AGILEGS_WARMUP)"}
        assert h.get("/healthz").status_code == 200  # alive, and serving
        assert h.get("/v1/sessions").status_code == 200
        release.set()
        for _ in range(300):
            if srv.server.warm == "done":
                break
            threading.Event().wait(0.05)
        assert h.get("/readyz").json() == {"ready": True}


def test_a_failed_warm_up_leaves_the_server_ready(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    def broken() -> dict[str, float]:
        raise RuntimeError("no compiler")

    monkeypatch.setattr(warmup, "warm_up", broken)
    with serve_in_process(tmp_path / "state", warmup=True) as srv, srv.http() as h:
        for _ in range(300):
            if srv.server.warm == "failed":
                break
            threading.Event().wait(0.05)
        assert srv.server.warm == "failed" and h.get("/readyz").status_code == 200


def test_no_warm_up_when_it_is_off(tmp_path: Path) -> None:
    with serve_in_process(tmp_path / "state") as srv, srv.http() as h:
        assert srv.server.warm is None and h.get("/readyz").status_code == 200

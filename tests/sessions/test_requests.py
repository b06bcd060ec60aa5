"""Writes applied once: a write sent again with its request id (a retry after a lost answer,
or after the session moved) is answered from the session's record and applies nothing; the
record survives a restart; an id names one write."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, make_core, ring_poses
from pydantic import BaseModel

from agilegs.client._requests import to_gaussians
from agilegs.schemas.requests import check_request_id, session_id_for
from agilegs.service.errors import ServiceError
from agilegs.service.sessions import requests as rq
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.transports.requests import parse_request

POOL = {"poses": [{"matrix": p.tolist()} for p in ring_poses(12)]}
BOUNDS = {"min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]}


def run(core: SessionRegistry, op: str, sid: str | None, payload: Any,
        rid: str | None = None) -> BaseModel:
    return core.execute(op, sid, parse_request(op, payload), request_id=rid)


def session(core: SessionRegistry, sid: str = "s") -> None:
    run(core, "create_session", None, {"id": sid, "intrinsics": SMALL_INTRINSICS,
                                       "bounds": BOUNDS, "init_gaussians": 200, "pool": POOL})


def test_a_write_sent_again_is_answered_again_and_applied_once(tmp_path: Path) -> None:
    core = make_core(tmp_path, mapper=False)
    session(core)
    first = run(core, "commit", "s", {"candidate_id": 3}, "commit-0001")
    version = core.session("s").record.version
    again = run(core, "commit", "s", {"candidate_id": 3}, "commit-0001")
    assert again == first and core.session("s").record.version == version
    assert [v.candidate_id for v in core.session("s").record.views] == [3]
    # without the id the same body is a new write (and candidate 3 is no longer in the pool)
    with pytest.raises(ServiceError) as err:
        run(core, "commit", "s", {"candidate_id": 3})
    assert err.value.status in (404, 409)
    # a select that commits: the decision comes back as it was, nothing is committed twice
    sel = run(core, "select", "s", {"method": "random", "commit": True}, "select-0001")
    views = len(core.session("s").record.views)
    again = run(core, "select", "s", {"method": "random", "commit": True}, "select-0001")
    # the same decision (core_ms as recorded before the commit; the first answer adds it)
    assert again.model_dump(exclude={"core_ms"}) == sel.model_dump(exclude={"core_ms"})
    assert len(core.session("s").record.views) == views
    # the pool: replaced once
    pool = run(core, "extend_pool", "s", POOL, "extend-0001")
    assert run(core, "extend_pool", "s", POOL, "extend-0001") == pool
    assert len(core.session("s").record.pool_ids) == len(pool.candidates)  # type: ignore[attr-defined]
    core.close()


def test_the_record_survives_a_restart(tmp_path: Path) -> None:
    core = make_core(tmp_path, mapper=False)
    session(core)
    first = run(core, "commit", "s", {"candidate_id": 5}, "restart-0001")
    core.close()
    core = make_core(tmp_path, mapper=False)
    assert run(core, "commit", "s", {"candidate_id": 5}, "restart-0001") == first
    assert len(core.session("s").record.views) == 1
    core.close()


def test_an_id_names_one_write(tmp_path: Path) -> None:
    core = make_core(tmp_path, mapper=False)
    session(core)
    run(core, "commit", "s", {"candidate_id": 1}, "one-write-01")
    before = core.session("s").record
    with pytest.raises(ServiceError) as err:
        run(core, "set_pool", "s", POOL, "one-write-01")
    assert err.value.status == 409 and err.value.field == "request_id"
    assert core.session("s").record is before
    core.close()


def test_old_answers_are_dropped_and_their_ids_kept(tmp_path: Path) -> None:
    core = make_core(tmp_path, mapper=False)
    session(core)
    ids = [f"old-answer-{k:03d}" for k in range(rq.KEEP_ANSWERS + 2)]
    for k, rid in enumerate(ids):
        run(core, "commit", "s", {"candidate_id": k % 12, "keep_in_pool": True}, rid)
    reqs = core.session("s").record.requests
    assert [r.id for r in reqs][-len(ids):] == ids
    assert sum(r.answer is not None for r in reqs) == rq.KEEP_ANSWERS
    views = len(core.session("s").record.views)
    with pytest.raises(ServiceError) as err:  # applied, its answer gone: never applied twice
        run(core, "commit", "s", {"candidate_id": 0, "keep_in_pool": True}, ids[0])
    assert err.value.status == 409 and "applied already" in err.value.message
    assert len(core.session("s").record.views) == views
    # an answer made from the session (set_gaussians answers the session's info) is remade
    g = to_gaussians({"means": np.zeros((4, 3)), "log_scales": np.full((4, 3), -2.0),
                      "quats": np.tile([1.0, 0, 0, 0], (4, 1)), "opacity_logits": np.zeros(4),
                      "sh": np.zeros((4, 1, 3))})
    run(core, "set_gaussians", "s", g, "set-gauss-001")
    for k in range(rq.KEEP_ANSWERS + 1):
        run(core, "commit", "s", {"candidate_id": k % 12, "keep_in_pool": True}, f"more-{k:04d}")
    version = core.session("s").record.version
    info = run(core, "set_gaussians", "s", g, "set-gauss-001")
    assert info.version == version == core.session("s").record.version  # type: ignore[attr-defined]
    core.close()


def test_the_kept_answers_fit_a_byte_budget(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    core = make_core(tmp_path, mapper=False)
    session(core)
    answers = [run(core, "commit", "s", {"candidate_id": 0, "keep_in_pool": True}, "sized-0000")]
    one = len(json.dumps(answers[0].model_dump(mode="json")))
    monkeypatch.setattr(rq, "ANSWERS_BUDGET", int(3.5 * one))
    for k in range(1, 7):
        answers.append(run(core, "commit", "s", {"candidate_id": k, "keep_in_pool": True},
                           f"sized-{k:04d}"))
    sizes = [len(json.dumps(a.model_dump(mode="json"))) for a in answers]
    want, total = [], 0  # the newest answers whose sizes fit the budget together
    for k in range(6, -1, -1):
        total += sizes[k]
        if total > rq.ANSWERS_BUDGET:
            break
        want.insert(0, f"sized-{k:04d}")
    reqs = core.session("s").record.requests
    assert 2 <= len(want) < 7
    assert [r.id for r in reqs if r.answer is not None] == want
    assert [r.id for r in reqs][-7:] == [f"sized-{k:04d}" for k in range(7)]  # ids all kept
    # a kept answer replays; one dropped is never applied twice
    views = len(core.session("s").record.views)
    again = run(core, "commit", "s", {"candidate_id": 6, "keep_in_pool": True}, "sized-0006")
    assert again.model_dump(mode="json") == reqs[-1].answer
    with pytest.raises(ServiceError) as err:
        run(core, "commit", "s", {"candidate_id": 1, "keep_in_pool": True}, "sized-0001")
    assert err.value.status == 409 and len(core.session("s").record.views) == views
    # the newest answer alone over the budget: none is kept (the newest that fit: none)
    monkeypatch.setattr(rq, "ANSWERS_BUDGET", one // 2)
    run(core, "commit", "s", {"candidate_id": 7, "keep_in_pool": True}, "sized-0007")
    assert all(r.answer is None for r in core.session("s").record.requests)
    core.close()


def test_a_create_without_id_is_named_by_its_request_id(tmp_path: Path) -> None:
    core = make_core(tmp_path, mapper=False)
    body = {"intrinsics": SMALL_INTRINSICS, "bounds": BOUNDS, "init_gaussians": 50}
    info = run(core, "create_session", None, body, "create-00001")
    assert info.id == session_id_for("create-00001")  # type: ignore[attr-defined]
    again = run(core, "create_session", None, body, "create-00001")
    assert again.id == info.id and len(core.sessions) == 1  # type: ignore[attr-defined]
    # an explicit id taken by another create is a conflict, as without request ids
    run(core, "create_session", None, {**body, "id": "mine"}, "create-00002")
    with pytest.raises(ServiceError) as err:
        run(core, "create_session", None, {**body, "id": "mine"}, "create-00003")
    assert err.value.status == 409
    core.close()


def test_request_ids_are_checked() -> None:
    assert check_request_id("0123456789abcdef0123456789abcdef")
    for bad in ("short", "x" * 65, "has space1", "slash/slash"):
        with pytest.raises(ValueError, match="request id"):
            check_request_id(bad)

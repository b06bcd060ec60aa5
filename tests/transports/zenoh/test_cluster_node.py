"""The cluster node in process: placement, instance ids and keys, the settings of several
instances, and a node with no Zenoh session (everything local). Two real instances joined
over Zenoh are in tests/e2e/test_cluster.py."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from agilegs import schemas as m
from agilegs.schemas.keys import instance_key, instances_wildcard, parse_instance_key
from agilegs.service.errors import ServiceError
from agilegs.service.settings import Settings
from agilegs.service.transports.zenoh.cluster import ClusterNode
from agilegs.service.transports.zenoh.placement import default_instance_id, placement_order


def test_placement_prefers_the_fewest_sessions_then_the_smallest_id() -> None:
    assert placement_order({"b": 0, "a": 0, "c": 1}) == ["a", "b", "c"]
    assert placement_order({"a": 3, "b": 1, "c": 1}) == ["b", "c", "a"]
    assert placement_order({"x": 0}) == ["x"]
    assert placement_order({}) == []


def test_instance_ids_and_keys() -> None:
    assert default_instance_id("gpu-box.lab.example.org", 8001) == "gpu-box-8001"
    assert default_instance_id("weird host!", 80) == "weird-host--80"
    assert instance_key("a", "health") == "agilegs/@instances/a/health"
    assert instances_wildcard("list_sessions") == "agilegs/@instances/*/list_sessions"
    assert parse_instance_key("agilegs/@instances/node-1.x/create_session") == (
        "node-1.x", "create_session")
    for bad in ("a/b", "*", "", "@x", "a b", "x" * 65):
        with pytest.raises(ValueError, match="instance"):
            instance_key(bad, "health")
    with pytest.raises(ValueError, match="op"):
        instance_key("a", "select")
    with pytest.raises(ValueError):
        parse_instance_key("agilegs/s1/select")


def test_settings_and_flags(tmp_path: Path) -> None:
    import pydantic

    from agilegs.service.cli import build_parser
    from agilegs.service.serve import build_settings

    args = build_parser().parse_args([
        "serve", "--instance-id", "gpu-1", "--zenoh-mode", "client", "--zenoh-connect",
        "tcp/10.0.0.1:7447", "--forward-timeout", "30", "--state-dir", str(tmp_path)])
    s = build_settings(args)
    assert (s.instance_id, s.zenoh_mode, s.zenoh_connect, s.forward_timeout) == (
        "gpu-1", "client", ["tcp/10.0.0.1:7447"], 30.0)
    with pytest.raises(pydantic.ValidationError):
        Settings(instance_id="a/b")
    with pytest.raises(pydantic.ValidationError):
        Settings(zenoh_mode="broker")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["serve", "--zenoh-mode", "broker"])


class _FakeRegistry:
    """What ClusterNode needs of a SessionRegistry."""

    fleet = False  # its sessions are in a state folder, not shared by a fleet

    def __init__(self) -> None:
        self.sessions: dict[str, Any] = {}

    def set_owner(self, instance_id: str) -> None:
        pass

    def health(self) -> m.Health:
        return m.Health(version="0", sessions=len(self.sessions), zenoh=False, uptime_s=0.0)


def test_a_detached_node_runs_everything_locally(tmp_path: Path) -> None:
    reg = _FakeRegistry()
    executor = ThreadPoolExecutor(1)
    settings = Settings(instance_id="solo", state_dir=tmp_path)
    node = ClusterNode(reg, settings, executor)  # type: ignore[arg-type]
    assert not node.attached and node.instance_id == "solo"
    calls: list[tuple[str, str | None]] = []

    def route(op: str, session: str | None, req: Any = None, **kw: Any) -> Any:
        def run_local() -> m.Deleted:
            calls.append((op, session))
            return m.Deleted(id=session or "x")

        return node.route(op, session, req, run_local=run_local, **kw)

    route("get_session", "s1")
    route("create_session", None, instance="solo")
    route("list_sessions", None)
    assert calls == [("get_session", "s1"), ("create_session", None), ("list_sessions", None)]
    with pytest.raises(ServiceError) as exc:
        route("create_session", None, instance="elsewhere")
    assert (exc.value.status, exc.value.code, exc.value.field) == (
        404, "instance_unavailable", "query.instance")
    with pytest.raises(ServiceError) as exc:
        route("create_session", None, instance="no/such")
    assert (exc.value.status, exc.value.field) == (422, "query.instance")
    assert calls == [("get_session", "s1"), ("create_session", None), ("list_sessions", None)]
    assert node.instances() == {"solo": reg.health()}
    other = ClusterNode(reg, Settings(port=8123, state_dir=tmp_path), executor)  # type: ignore[arg-type]
    assert other.instance_id.endswith("-8123")
    executor.shutdown()

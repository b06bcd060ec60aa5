"""``agilegs serve --ros2``: a session driven only by ROS 2 messages on Zenoh (CDR on the keys
zenoh-bridge-ros2dds uses) reaches the same decisions as the same session driven by the
Python client over HTTP; the example robot script runs against it; the deploy files load.

Peers meet on a loopback TCP endpoint with multicast and gossip scouting off.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import ROOT, SMALL_INTRINSICS, ServerProcess, ring_poses

from agilegs.client import Client
from agilegs.client.ros2.frames import matrix_to_pose_msg, pose_msg_to_matrix
from agilegs.client.ros2.robot import Ros2Robot
from agilegs.schemas import ObservationIn, PoolIn, Pose, SelectResponse

NS = "/bot/agilegs"
DEMO_NS = "/demo/agilegs"
H, W = SMALL_INTRINSICS["height"], SMALL_INTRINSICS["width"]
BOUNDS = ([-0.5] * 3, [0.5] * 3)
OPTIONS: dict[str, Any] = {
    "init_gaussians": 150,
    "seed": 3,
    "defaults": {"shortlist_size": 4,
                 "config": {"anchor": {"iterations": 1, "num_starts": 2}}},
    "mapper": {"steps_per_view": 3, "config": {"sh_degree": 0, "densify_from": 1000}},
}


@pytest.fixture(scope="module")
def ros2_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    root = tmp_path_factory.mktemp("ros2")
    srv = ServerProcess(root / "state", env={"AGILEGS_MAPPER": "1"},
                        args=["--ros2", f"{NS},{DEMO_NS}"]).start()
    yield srv
    srv.stop()


def _wire(c2w: np.ndarray) -> Pose:
    """The pose as a robot's message carries it (position + quaternion)."""
    msg = matrix_to_pose_msg(c2w)
    p, q = msg.position, msg.orientation
    return Pose.from_position_quaternion([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])


def _observation(c2w: np.ndarray, rgb: np.ndarray, mm: np.ndarray) -> ObservationIn:
    """The frame a robot publishes, as the Python client sends it."""
    return ObservationIn.from_numpy(_wire(c2w), image=rgb, depth=mm, depth_scale=0.001,
                                    intrinsics=SMALL_INTRINSICS)


def _frame(i: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(i)
    return (rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
            rng.integers(800, 3000, (H, W), dtype=np.uint16))


def _idle(client: Client, sid: str, views: int, timeout: float = 120.0) -> None:
    """Wait until the session holds ``views`` views and its mapper trained on all of them."""
    deadline = time.monotonic() + timeout
    while True:
        info = client.get_session(sid)
        assert info.mapper is not None and info.mapper.state != "error", info.mapper
        if info.num_views == views and info.mapper.state == "idle" \
                and info.mapper.pending_steps == 0:
            return
        assert time.monotonic() < deadline, f"{sid}: {info.num_views} views, {info.mapper}"
        time.sleep(0.05)


def test_a_ros2_session_decides_as_a_python_client_session(ros2_server: ServerProcess) -> None:
    pool = ring_poses(10)
    methods = ["agile", "agile_plus", "fisherrf"]
    with Client(ros2_server.url, timeout=120) as client, \
            Ros2Robot(NS, connect=[ros2_server.zenoh_endpoint], timeout=120) as robot:
        # the robot: camera, session, pool and two frames, all as ROS 2 messages
        robot.publish_camera_info(SMALL_INTRINSICS)
        made = robot.create_session(bounds=BOUNDS, session="via-ros2", expect_depth=True,
                                    options=OPTIONS)
        assert made.status.status == 200, made.status
        robot.publish_candidates(pool)
        # the same through the client
        client.create_session(SMALL_INTRINSICS, id="via-python",
                              bounds={"min": BOUNDS[0], "max": BOUNDS[1]},
                              init_gaussians=OPTIONS["init_gaussians"], seed=OPTIONS["seed"],
                              defaults=OPTIONS["defaults"], mapper=OPTIONS["mapper"])
        client.set_pool("via-python", PoolIn(poses=[_wire(p) for p in pool]))
        visited: list[int] = []

        def drive_to(i: int, stamp: int) -> None:
            """Both robots capture pool[i]; the mappers train on it before anything else."""
            visited.append(i)
            rgb, mm = _frame(i)
            robot.publish_frame(rgb, pool[i], depth=mm, stamp_ns=stamp)
            client.add_observations("via-python", _observation(pool[i], rgb, mm))
            for sid in ("via-ros2", "via-python"):
                _idle(client, sid, len(visited))

        drive_to(0, 1)
        drive_to(5, 2)
        for step, method in enumerate(methods):
            answer = robot.select(method=method)
            assert answer.status.status == 200, answer.status
            expected: SelectResponse = client.select("via-python", method=method)
            assert answer.chosen_id == expected.chosen.id, (method, step)
            assert list(answer.shortlist_ids) == [c.id for c in expected.shortlist]
            want = [np.nan if c.score is None else c.score for c in expected.shortlist]
            np.testing.assert_array_equal(answer.shortlist_scores, want)
            np.testing.assert_allclose(pose_msg_to_matrix(answer.chosen.pose),
                                       expected.chosen.pose.to_matrix(), atol=1e-9)
            assert answer.has_anchor == (expected.anchor is not None)
            assert answer.version == expected.version
            drive_to(answer.chosen_id, 10 + step)
        a = client.get_information("via-ros2").summary.digest
        b = client.get_information("via-python").summary.digest
        assert a == b  # the same views, the same Ĥ
        views = client.list_views("via-ros2").views
        assert [v.has_depth for v in views] == [True] * len(visited)


def test_the_example_robot_script_runs(ros2_server: ServerProcess) -> None:
    script = ROOT / "deploy" / "ros2" / "play_robot.py"
    out = subprocess.run([sys.executable, str(script), "--quick", "--events", "1",
                          "--method", "agile", "--connect", ros2_server.zenoh_endpoint,
                          "--namespace", DEMO_NS], capture_output=True, text=True,
                         timeout=300, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "event 1: candidate" in out.stdout
    assert "3 views acquired" in out.stdout  # 2 initial frames + 1 event


def test_the_bridge_config_and_launch_file_load() -> None:
    import zenoh

    conf = zenoh.Config.from_file(str(ROOT / "deploy" / "ros2" / "zenoh-bridge-ros2dds.json5"))
    plugin = conf.get_json("plugins/ros2dds")
    assert '"namespace"' in plugin and "agilegs/select" in plugin
    # closed as the server is: its users file, its user, access control on the agilegs keys
    from agilegs.service.transports.zenoh.security import ACL_MESSAGES, OWN_USER

    assert json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file"))
    assert json.loads(conf.get_json("transport/auth/usrpwd/user")) == OWN_USER
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert acl["rules"][0]["messages"] == ACL_MESSAGES
    assert "bot1/agilegs/**" in acl["rules"][0]["key_exprs"]
    assert [(s["id"], s["usernames"]) for s in acl["subjects"]] == [("agilegs-users",
                                                                     [OWN_USER])]
    for name in ("agilegs_robot.launch.py", "camera_pose_node.py"):
        ast.parse((ROOT / "deploy" / "ros2" / name).read_text())
    assert (ROOT / "deploy" / "ros2" / "agilegs_interfaces" / "package.xml").is_file()


def test_serve_refuses_ros2_without_zenoh(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "agilegs.service.cli", "serve", "--no-zenoh",
                          "--ros2", NS, "--state-dir", str(tmp_path / "s")],
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode != 0 and "AGILEGS_ZENOH" in out.stderr


def test_bench_service_times_the_ros2_service(ros2_server: ServerProcess) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "bench", "service", "--url",
         ros2_server.url, "--zenoh", ros2_server.zenoh_endpoint, "--ros2", DEMO_NS,
         "--requests", "5", "--warmup", "1", "--pool", "30", "--max-gaussians", "100",
         "--size", "16", "--clients", "1", "--selections", "1", "--phases", "overhead,load"],
        capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    row = next(line for line in proc.stdout.splitlines() if line.startswith("ros2/preset"))
    assert float(row.split()[1]) > 0  # the overhead's p50, in ms

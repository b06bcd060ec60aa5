"""Play a ROS 2 robot against agilegs over Zenoh, with ROS 2 messages only (no ROS install).

What a robot behind zenoh-bridge-ros2dds sends and receives, as CDR on the bridge's keys
(``agilegs.client.ros2.robot.Ros2Robot``): its camera (``camera_info``), a session made with
``create_session``, the candidate pool (``candidates``, a PoseArray), posed RGB-D frames
(``image`` rgb8, ``depth`` 32FC1 metres and ``camera_pose`` sharing a stamp) and a ``select``
call per event, whose reply is the chosen view (a PoseStamped). The frames are rendered from
a bundled ground-truth splat (the demo's simulated robot, ``agilegs demo``), so the server's
mapper trains on them as it would on a real camera's.

    python deploy/ros2/play_robot.py                 # starts agilegs serve --ros2 itself
    python deploy/ros2/play_robot.py --connect tcp/127.0.0.1:7447 --namespace /bot1/agilegs

Needs the server install (``pip install 'agilegs[service]'``) for the rendering.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--connect", help="the server's Zenoh endpoint (default: start a server)")
    p.add_argument("--namespace", default="/demo/agilegs", help="the ROS 2 namespace served")
    p.add_argument("--method", default="agile_plus", help="selection method (agile_plus)")
    p.add_argument("--events", type=int, default=None, help="selection events")
    p.add_argument("--scene", default="spot", help="spot or teapot, or a .splat / .ply file")
    p.add_argument("--quick", action="store_true", help="32x32 images, 2 events (tests)")
    args = p.parse_args(argv)

    from agilegs.client.ros2.robot import Ros2Robot
    from agilegs.lab.demo.run import FULL, QUICK, Robot, initial_indices, mapper_options
    from agilegs.service.launch import ServerProcess
    from agilegs.service.nbv.candidates import scene_center_radius

    size = QUICK if args.quick else FULL
    events = args.events if args.events is not None else size.events
    sim = Robot(args.scene, size, seed=0)
    pool = sim.pool.double().numpy()  # [D, 4, 4] camera-to-world, OpenCV axes
    c, r98 = scene_center_radius(sim.gt.means)
    center, half = c.double().numpy(), 1.2 * float(r98)
    server = None
    if args.connect is None:
        state = Path(tempfile.mkdtemp(prefix="agilegs-ros2-"))
        server = ServerProcess(state / "state", http=False, args=["--ros2", args.namespace],
                               env={"AGILEGS_TORCH_THREADS": "1"}).start()
    endpoint = args.connect or server.zenoh_endpoint  # type: ignore[union-attr]
    out = sys.stdout
    try:
        with Ros2Robot(args.namespace, connect=[endpoint], timeout=600) as robot:
            robot.publish_camera_info(sim.intrinsics)
            made = robot.create_session(
                bounds=(center - half, center + half), expect_depth=True,
                options={"init_gaussians": size.init_gaussians,
                         "mapper": mapper_options(size, sim),
                         "defaults": {"shortlist_size": size.shortlist_size}})
            if made.status.status != 200:
                out.write(f"create_session refused: {made.status.message}\n")
                return 1
            out.write(f"session {made.session} on {args.namespace}\n")
            stamp = 1
            visited: list[int] = []

            def capture(i: int) -> None:
                nonlocal stamp
                rgb, depth = sim.capture(pool[i])
                robot.publish_frame(rgb, pool[i], depth=depth, stamp_ns=stamp)
                stamp += 1
                visited.append(i)

            for i in initial_indices(len(pool), size.initial_views):
                capture(i)
            for event in range(events):
                left = [i for i in range(len(pool)) if i not in visited]
                robot.publish_candidates(pool[left])
                t0 = time.perf_counter()
                answer = robot.select(method=args.method)
                if answer.status.status != 200:
                    out.write(f"select refused: {answer.status.message}\n")
                    return 1
                p = answer.chosen.pose.position
                chosen = min(left, key=lambda i: float(np.linalg.norm(
                    pool[i][:3, 3] - [p.x, p.y, p.z])))
                out.write(f"event {event + 1}: candidate {answer.chosen_id} (pool index "
                          f"{chosen}), selection {answer.latency_ms:.0f} ms, round trip "
                          f"{(time.perf_counter() - t0) * 1e3:.0f} ms\n")
                capture(chosen)
            opened = robot.open_session(made.session, expect_depth=True)
            out.write(f"{opened.num_views} views acquired\n")
    finally:
        if server is not None:
            server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

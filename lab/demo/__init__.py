"""``agilegs demo``: the closed loop on a bundled scene or a posed capture (:mod:`.run`), with
the robot that replays a capture (:mod:`.capture_robot`)."""

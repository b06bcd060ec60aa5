"""The persistent session store: what a session holds (:mod:`.records`), writing it
(:mod:`.write`), reading it back and checking it (:mod:`.read`, :mod:`.integrity`), and the
server's state folder held exclusively while it runs (:mod:`.state_dir`)."""

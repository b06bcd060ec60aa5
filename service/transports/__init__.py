"""The transports: HTTP (:mod:`.http`), Zenoh (:mod:`.zenoh`, with the routing of a session's
operations to the instance of a cluster that holds it) and ROS 2 over Zenoh (:mod:`.ros2`),
and what every transport shares: the request pipeline (:mod:`.gateway`) and its validation
step (:mod:`.requests`), what a request may cost (:mod:`.admission`) and the metrics
(:mod:`.metrics`). No maths here: a transport turns what arrived into a gateway request and the
reply back."""

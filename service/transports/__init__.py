"""The transports: HTTP (:mod:`.http`), Zenoh (:mod:`.zenoh`) and ROS 2 over Zenoh
(:mod:`.ros2`), and what every transport shares: the request pipeline (:mod:`.gateway`), what
a request may cost (:mod:`.admission`), the metrics (:mod:`.metrics`) and the routing of a
session's operations to the instance of a cluster that holds it (:mod:`.cluster`). No maths
here: a transport turns what arrived into a gateway request and the reply back."""

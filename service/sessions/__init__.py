"""The sessions of the server: conversions from the wire (:mod:`.convert`), every change of a
session's state as a function of its record (:mod:`.transitions`, the select step in
:mod:`.selection`), one session's lock, persistence and reads (:mod:`.session`), the mapper's
bookkeeping (:mod:`.mapper_state`) and its background trainer (:mod:`.trainer`), and the
registry that names each operation's handler (:mod:`.registry`)."""

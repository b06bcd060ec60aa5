"""The sessions of the server: conversions from the wire (:mod:`.convert`), one session's
state machine (:mod:`.session`, :mod:`.selection`), the mapper's bookkeeping
(:mod:`.mapper_state`) and the registry that names each operation's handler
(:mod:`.registry`)."""

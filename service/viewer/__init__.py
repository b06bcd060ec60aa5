"""agilegs.service.viewer: a live browser view of a session, and the replay of a benchmark
run (``agilegs view``), drawn with viser (``pip install "agilegs[viewer]"``).

The viewer is a client of the service (the SDK over HTTP, or Zenoh), never part of the
server's process, and needs no torch. Modules: :mod:`.live` (:class:`SessionViewer`),
:mod:`.replay` (:class:`RunReplay`), :mod:`.canvas` (the 3D scene), :mod:`.panel` (the side
panel), :mod:`.scene` (numpy conversions), :mod:`.browser` (a headless screenshot),
:mod:`.cli` (the command). Importing this package does not import viser.
"""

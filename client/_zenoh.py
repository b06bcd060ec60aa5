"""Zenoh session configuration shared by the server and :class:`ZenohClient` (no torch)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

__all__ = ["peer_config"]


def peer_config(
    listen: Sequence[str] = (), connect: Sequence[str] = (), mode: str = "peer"
) -> Any:
    """A ``zenoh.Config``: ``mode`` (peer by default), explicit listen / connect endpoints,
    multicast and gossip scouting off (peers meet only through the endpoints given)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return conf

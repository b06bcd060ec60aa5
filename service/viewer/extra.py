"""viser, the viewer's one extra dependency (``pip install "agilegs[viewer]"``)."""

from __future__ import annotations

import io
import logging
from collections.abc import Iterator
from contextlib import contextmanager, redirect_stdout
from types import ModuleType

__all__ = ["INSTALL", "ViewerMissing", "quiet", "require_viser"]

log = logging.getLogger(__name__)

INSTALL = 'pip install "agilegs[viewer]"'
"""The command that installs the viewer's extra."""


class ViewerMissing(RuntimeError):
    """viser is not installed; the message says how to install it (one line)."""


def require_viser() -> ModuleType:
    """The ``viser`` module, or :class:`ViewerMissing` naming the install command."""
    try:
        import viser
    except ImportError as exc:
        raise ViewerMissing(f"the viewer needs viser (missing {exc.name or 'viser'!r}): "
                            f"{INSTALL}") from None
    return viser


@contextmanager
def quiet(what: str) -> Iterator[None]:
    """Keep what viser prints on stdout (its banner, "Server stopped") out of the caller's
    output: it goes to this module's debug log instead."""
    buf = io.StringIO()
    with redirect_stdout(buf):
        yield
    text = buf.getvalue().strip()
    if text:
        log.debug("viser (%s): %s", what, text)

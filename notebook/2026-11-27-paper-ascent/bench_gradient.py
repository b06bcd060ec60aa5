"""`agilegs bench latency` with the exact psi's gradient forced to the first argument.

Ran at commit 6a84c7c: ``python bench_gradient.py autograd ARGS...`` times ``@paper`` with the
gradient by autograd through the torch path (the path before that commit), ``forward`` or
``central`` with differences of compiled values; ARGS are ``bench latency``'s.
"""

import sys

from agilegs.service.cli import main
from agilegs.service.nbv.anchor import exact

MODE = sys.argv.pop(1)
_init = exact.ExactPsi.__init__


def _forced(self, *args, **kwargs):  # type: ignore[no-untyped-def]
    kwargs["gradient"] = MODE
    _init(self, *args, **kwargs)


exact.ExactPsi.__init__ = _forced  # type: ignore[method-assign]
sys.exit(main(["bench", "latency", *sys.argv[1:]]))

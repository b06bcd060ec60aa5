"""The selection methods, one module each, registered by name (see :mod:`.base`).

- ``random`` (:mod:`.random`): a seeded uniform choice.
- ``spread`` (:mod:`.spread`): farthest-point sampling, the eligible candidate farthest from
  every acquired view (position and rotation); needs neither the map nor Hhat.
- ``fisherrf`` (:mod:`.fisherrf`): FisherRF as its code computes it (trace score against a
  Hessian rebuilt from the acquired views), argmax.
- ``cover`` (:mod:`.cover`): COVER's coverage score, argmin.
- ``full_eig`` (:mod:`.full_eig`): the exact diagonal EIG of every eligible candidate, argmax.
- ``agile``, ``agile_plus`` (:mod:`.agile`): the anchor, the coverage matrix, the leverage
  shortlist; its first, or its best under the exact EIG.

To add a method: write a module here with a class that has ``name``, ``uses_information`` and
``__call__(context) -> MethodResult``, ``register`` an instance,
add its module to :data:`MODULES` and its name to ``Method`` in
:mod:`agilegs.config.selection` (the settings the maths and the wire contract share).
"""

import importlib

from .base import (
    STAGES,
    MethodResult,
    SelectionContext,
    SelectionMethod,
    get_method,
    method_names,
    register,
)

__all__ = [
    "MODULES",
    "STAGES",
    "MethodResult",
    "SelectionContext",
    "SelectionMethod",
    "get_method",
    "method_names",
    "register",
]

MODULES: tuple[str, ...] = ("random", "spread", "fisherrf", "cover", "full_eig", "agile")
"""The method modules, imported (so registered) in this order: the order methods are listed in."""

for _module in MODULES:
    importlib.import_module(f"{__name__}.{_module}")

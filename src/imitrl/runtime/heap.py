"""The import-time heap and Python's cyclic garbage collector, in a process imitrl owns.

An imitrl command imports torch, tensordict (which imports ``torch._dynamo`` and sympy),
torchrl and gymnasium: 300,000 to 430,000 objects tracked by the cyclic collector (about
390,000 for ``imitrl gail``), which
live until the process ends. Every full collection walks all of them (0.2 s on the
2-core machines this project is measured on), and at interpreter exit, once the modules
are cleared, the collector finds them garbage and frees them one by one: a process that
imports imitrl's GAIL path and exits spent 1.2-1.3 s in that exit, 0.15-0.2 s with the
heap frozen first (``benchmarks/README.md``, ``peer_gail``).

:func:`freeze_imported` moves every object tracked at that moment into the collector's
permanent generation (``gc.freeze``), which no collection walks again: the objects are
untouched and stay alive (they would anyway: modules, functions, classes), collections
during the run look at what the run creates, and the exit leaves the frozen objects to the
operating system instead of freeing them one by one.
What it costs: garbage cycles that exist at the moment of the freeze are never freed
(a one-off, the import's leftovers: none in an ``imitrl gail`` process, where
``gc.collect()`` just before the freeze finds nothing), nor is a frozen object that
becomes cyclic garbage later in the run, and the ``__del__`` of an object in such a
cycle never runs.

Only a process's owner should call it: the command line (:func:`imitrl.cli.main`) calls
it once a command's modules are imported, before the command runs; the benchmarks'
imitrl children call it where the command line would. A library call
(``imitrl.algorithms.gail(...)`` in a user's program) never freezes the user's heap.
"""

from __future__ import annotations

import gc

__all__ = ["freeze_imported"]


def freeze_imported() -> int:
    """Move every object the cyclic collector tracks now into its permanent generation.

    Returns the number of objects frozen so far (``gc.get_freeze_count()``).
    """
    gc.freeze()
    return gc.get_freeze_count()

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

The collector also walks the heap *while* it is being imported: with automatic
collection on, an ``imitrl gail`` process's imports ran six full collections over a heap
growing to about 620,000 tracked objects, 3.5-3.65 s of imports against 2.4-2.5 s with
the collector paused (two runs each, one thread, load 0.2). :func:`collector_paused`
pauses it (``gc.disable``) for the imports and puts it back as it was. What that costs:
the cyclic garbage the imports leave (about 10,000 objects in an ``imitrl gail`` process,
found by a ``gc.collect()`` after paused imports, which itself takes 0.4-0.5 s) is frozen
with the rest and never freed; the run's own garbage is collected as usual.

Only a process's owner should call them: the command line (:func:`imitrl.cli.main`)
imports a command's modules with the collector paused and freezes the heap before the
command runs; the benchmarks' imitrl children do what the command line does. A library
call (``imitrl.algorithms.gail(...)`` in a user's program) never touches the user's
collector or heap.
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator

__all__ = ["collector_paused", "freeze_imported"]


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """Within: no automatic collection (``gc.disable``); after, even on an error, the
    collector enabled again if it was (module docstring)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def freeze_imported() -> int:
    """Move every object the cyclic collector tracks now into its permanent generation.

    Returns the number of objects frozen so far (``gc.get_freeze_count()``).
    """
    gc.freeze()
    return gc.get_freeze_count()

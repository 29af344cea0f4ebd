"""How many CPU threads torch uses (:func:`set_threads`), and the default's reason.

torch starts with one intra-op thread per core. On the 2-core machines this project is
measured on, two threads made 100 ``fit_bc`` steps 2.6x to 6.3x slower than one beside
a single busy core (another test, a second job, the OS), while on a quiet machine they
saved 20-35% of a small CNN's time and at most 20% on a 64-64 MLP: each op
waits for its slowest thread, and a thread that shares its core waits for the core
(oversubscription; a plain torch loop slows the same way). Measured by
``benchmarks/threads.py`` (numbers and machine load in ``benchmarks/README.md``), the
default is therefore :data:`DEFAULT_THREADS` = 1 for every command (``--threads N``
changes it); workers that run side by side (``--jobs`` in the benchmarks, the Ray
workers of :class:`~imitrl.algorithms.ray_source.RaySource`) run one thread each, and
:func:`worker_threads` gives a pool of one's own its share, never more threads in all
than the machine has cores.

This module imports torch only when :func:`set_threads` runs, so the command line's
``--help`` (which shows :data:`DEFAULT_THREADS`) starts without it.
"""

from __future__ import annotations

import os

__all__ = ["DEFAULT_THREADS", "cores", "set_threads", "worker_threads"]

DEFAULT_THREADS = 1
"""torch's intra-op threads in every command unless ``--threads`` says otherwise
(``benchmarks/threads.py`` measured why)"""


def _check(name: str, value: object) -> int:
    """``value`` as an int >= 1, or ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return value


def cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def set_threads(threads: int | None = None) -> int:
    """Set torch's intra-op threads in this process (None: :data:`DEFAULT_THREADS`).

    Returns the number set. Call it before torch's first parallel op: the threads of an
    op already running are not changed.

    Raises:
        ValueError: not an integer >= 1.
    """
    n = DEFAULT_THREADS if threads is None else _check("threads", threads)
    import torch  # here: importing this module (the CLI's --help) must not import torch

    torch.set_num_threads(n)
    return n


def worker_threads(workers: int, threads: int | None = None) -> int:
    """Threads for each of ``workers`` processes that run at once on this machine.

    ``threads`` (None: :data:`DEFAULT_THREADS`) capped at the cores divided among the
    workers (rounded down, at least one), so that ``workers * worker_threads(workers)``
    never exceeds :func:`cores` while a worker has a core of its own.

    Raises:
        ValueError: ``workers`` or ``threads`` not an integer >= 1.
    """
    want = DEFAULT_THREADS if threads is None else _check("threads", threads)
    return max(1, min(want, cores() // _check("workers", workers)))

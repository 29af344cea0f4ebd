"""What the process computes on: the device, torch's threads, the garbage collector's heap.

* :mod:`imitrl.system.device`: ``device=`` / ``--device`` (:func:`resolve_device`), the
  learner's device (:func:`module_device`), batches moved to it (:func:`to_device`), a
  policy acting in an env on another device (:class:`OnDevice`, :func:`acting`).
* :mod:`imitrl.system.threads`: torch's intra-op threads (:func:`set_threads`, default
  :data:`DEFAULT_THREADS` = 1, measured in ``benchmarks/threads.py``) and each worker's
  share when several run at once (:func:`worker_threads`).
* :mod:`imitrl.system.ranks`: data-parallel ranks on ``torch.distributed``
  (:func:`rank_and_world`), a fit's gradients shared among them (:class:`DataParallel`).
* :mod:`imitrl.system.heap`: in a process imitrl owns, its imports with the garbage
  collector paused (:func:`~imitrl.system.heap.collector_paused`), then the import-time
  heap frozen out of the collector's walks (:func:`~imitrl.system.heap.freeze_imported`).

These are the leaves every layer may use; nothing here imports another part of imitrl
but :mod:`imitrl.keys`. Each name is imported from its module on first use (PEP 562):
the command line reads :data:`DEFAULT_THREADS` for its ``--help`` without importing torch.
"""

from imitrl import _lazy_exports

__all__ = [
    "DEFAULT_THREADS",
    "DataParallel",
    "OnDevice",
    "acting",
    "cores",
    "module_device",
    "rank_and_world",
    "resolve_device",
    "set_threads",
    "to_device",
    "worker_threads",
]

__getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "DEFAULT_THREADS": "imitrl.system.threads",
        "cores": "imitrl.system.threads",
        "set_threads": "imitrl.system.threads",
        "worker_threads": "imitrl.system.threads",
        "DataParallel": "imitrl.system.ranks",
        "rank_and_world": "imitrl.system.ranks",
        "OnDevice": "imitrl.system.device",
        "acting": "imitrl.system.device",
        "module_device": "imitrl.system.device",
        "resolve_device": "imitrl.system.device",
        "to_device": "imitrl.system.device",
    },
)

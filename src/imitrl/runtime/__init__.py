"""One runtime on any device: where a learner computes, its threads, the rollout loop.

* :mod:`imitrl.runtime.device`: ``device=`` / ``--device`` (:func:`resolve_device`), the
  learner's device (:func:`module_device`), batches moved to it (:func:`to_device`), a
  policy acting in an env on another device (:class:`OnDevice`, :func:`acting`).
* :mod:`imitrl.runtime.threads`: torch's intra-op threads (:func:`set_threads`, default
  :data:`DEFAULT_THREADS` = 1, measured in ``benchmarks/threads.py``) and each worker's
  share when several run at once (:func:`worker_threads`).
* :mod:`imitrl.runtime.heap`: in a process imitrl owns, its imports with the garbage
  collector paused (:func:`~imitrl.runtime.heap.collector_paused`), then the import-time
  heap frozen out of the collector's walks (:func:`~imitrl.runtime.heap.freeze_imported`).
* :mod:`imitrl.runtime.loop`: the one rollout loop (:func:`~imitrl.runtime.loop.play`)
  that collection, relabelling and evaluation share, over a ``Stepper``.
* :mod:`imitrl.runtime.reference`: the reference stepper, on public TorchRL alone.
* :mod:`imitrl.runtime.paths`: the seam that chooses between each reference and its
  accelerated form in :mod:`imitrl.runtime.fast` (the only module that imports it);
  ``with paths.reference():`` runs everything on the reference paths.

Each name is imported from its module on first use (PEP 562): the command line reads
:data:`DEFAULT_THREADS` for its ``--help`` without importing torch.
"""

from imitrl import _lazy_exports

__all__ = [
    "DEFAULT_THREADS",
    "OnDevice",
    "acting",
    "cores",
    "module_device",
    "resolve_device",
    "set_threads",
    "to_device",
    "worker_threads",
]

__getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "DEFAULT_THREADS": "imitrl.runtime.threads",
        "cores": "imitrl.runtime.threads",
        "set_threads": "imitrl.runtime.threads",
        "worker_threads": "imitrl.runtime.threads",
        "OnDevice": "imitrl.runtime.device",
        "acting": "imitrl.runtime.device",
        "module_device": "imitrl.runtime.device",
        "resolve_device": "imitrl.runtime.device",
        "to_device": "imitrl.runtime.device",
    },
)

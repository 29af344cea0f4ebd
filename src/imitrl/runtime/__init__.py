"""Where a learner computes and how many CPU threads it uses.

* :mod:`imitrl.runtime.device`: ``device=`` / ``--device`` (:func:`resolve_device`), the
  learner's device (:func:`module_device`), batches moved to it (:func:`to_device`), a
  policy acting in an env on another device (:class:`OnDevice`, :func:`acting`).
* :mod:`imitrl.runtime.threads`: torch's intra-op threads (:func:`set_threads`, default
  :data:`DEFAULT_THREADS` = 1, measured in ``benchmarks/threads.py``) and each worker's
  share when several run at once (:func:`worker_threads`).

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

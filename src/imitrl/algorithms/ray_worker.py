"""What each Ray worker of :class:`~imitrl.algorithms.ray_source.RaySource` runs with.

The driver (``ray_source``) plans slots and gathers rows; this module is the worker's
side: its TorchRL ``Collector`` (:class:`EpisodeCollector`, one Ray actor each), the env
it builds (:func:`worker_env`: the user's, in an ``InitTracker`` when a chunked learner
needs one), its copy of the behaviour policy (:func:`worker_policy`) and the errors it
sends back (:class:`WorkerFailure`).
"""

from __future__ import annotations

import builtins
import copy
import functools
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms.ray_setup import WORKER_THREADS
from imitrl.policies.mixture import BetaMixer
from imitrl.runtime.rollout import NEXT_KEYS, OPTIONAL_ROW_KEYS, ROW_KEYS, init_tracked
from imitrl.system.device import OnDevice
from imitrl.system.threads import set_threads

__all__ = ["EpisodeCollector", "WorkerFailure", "worker_env", "worker_policy"]

_KEEP = (*ROW_KEYS, *[(keys.NEXT, k) for k in NEXT_KEYS])


class EpisodeCollector(Collector):
    """A TorchRL ``Collector`` (one per Ray actor) that plays a seeded slot of whole episodes.

    Built by ``RayCollector`` with ``trajs_per_batch=1, traj_format="cat"``: each
    ``next()`` is one whole episode (the inner collector holds unfinished ones back).
    Its process runs :data:`WORKER_THREADS` torch threads, set before the collector is.
    """

    def __init__(self, *args, **kwargs) -> None:  # Collector's own, as RayCollector passes them
        set_threads(WORKER_THREADS)  # this actor's process, before its first torch op
        super().__init__(*args, **kwargs)

    def play_episodes(
        self, env_seed: int, torch_seed: int, num_episodes: int, exploration: ExplorationType
    ) -> tuple[TensorDict, float]:
        """``num_episodes`` whole episodes back to back (``[T]``), and the seconds they took;
        an error the env or the policy raised comes back as a :class:`WorkerFailure`
        (Ray 2.x turns it into a dead worker instead: the driver would lose the message)."""
        start = time.perf_counter()
        try:
            self.exploration_type = exploration
            self.set_seed(env_seed)
            self.reset()  # a fresh initial state; drops episodes left from the last call
            torch.manual_seed(torch_seed)  # this process: the learner's and mixer's draws
            episodes = [self.next() for _ in range(num_episodes)]
            rows = TensorDict.cat(episodes).select(*_KEEP, *OPTIONAL_ROW_KEYS, strict=False)
        except Exception as err:
            return WorkerFailure.of(err), time.perf_counter() - start
        return rows, time.perf_counter() - start

    def __repr__(self) -> str:  # Ray prefixes the actor's log lines with it: keep it one line
        return f"{type(self).__name__}(worker {self.worker_idx})"


@dataclass(frozen=True)
class WorkerFailure:
    """An exception a worker's env or policy raised, carried back to the driver as a value."""

    kind: str
    """the exception's class name"""
    message: str
    trace: str
    """the worker's traceback"""

    @classmethod
    def of(cls, err: BaseException) -> WorkerFailure:
        return cls(type(err).__name__, str(err), traceback.format_exc())

    def error(self, slot: int) -> Exception:
        """The exception to raise in the driver: the worker's builtin exception type (a
        ValueError stays a ValueError), else RuntimeError, naming the slot and the type."""
        kind = getattr(builtins, self.kind, None)
        cls = kind if isinstance(kind, type) and issubclass(kind, Exception) else RuntimeError
        return cls(
            f"Ray worker slot {slot} failed: {self.kind}: {self.message}\n"
            f"(in the worker:)\n{self.trace}"
        )


def worker_policy(behaviour: TensorDictModuleBase) -> TensorDictModuleBase:
    """The copy of ``behaviour`` the workers are built with: on the CPU, same weight keys.

    Parameters and buffers are moved to the CPU and every :class:`OnDevice` wrapper (a
    learner on CUDA acting in a CPU env) is told its module is there now, so the
    driver's broadcast weights load as they are; a ``BetaMixer`` draws its coins from the
    worker's seeded torch RNG. The caller's module is left as it is.
    """
    policy = copy.deepcopy(behaviour).cpu()
    for module in policy.modules():
        if isinstance(module, OnDevice):
            module.device = torch.device("cpu")
        elif isinstance(module, BetaMixer):
            module.generator = None
    return policy


def worker_env(
    make_env: Callable[[], EnvBase], env: EnvBase, policy: TensorDictModuleBase
) -> Callable[[], EnvBase]:
    """The ``make_env`` the workers call: ``make_env`` itself, or, when ``policy`` reads
    ``"is_init"`` (a chunked learner) and ``env`` (the driver's copy) does not write it,
    ``make_env`` followed by :func:`~imitrl.runtime.rollout.init_tracked`, as a local rollout
    wraps it: so DAgger with a chunked learner runs on workers with the user's plain env."""
    if init_tracked(env, policy) is env:
        return make_env
    return functools.partial(_tracked_env, make_env)


def _tracked_env(make_env: Callable[[], EnvBase]) -> EnvBase:
    """``make_env()`` in TorchRL's ``InitTracker``, as :func:`init_tracked` wraps it
    (a module-level function: the workers unpickle and call it)."""
    return TransformedEnv(make_env(), InitTracker(), auto_unwrap=False)

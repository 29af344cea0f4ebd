"""DAgger's relabel rounds on N Ray workers: :class:`RaySource`, an ``EpisodeSource``.

Each worker is a TorchRL :class:`~torchrl.collectors.Collector` running as a Ray actor,
built by TorchRL's :class:`~torchrl.collectors.distributed.RayCollector`. It holds its
own env (built by ``make_env()`` in the worker) and a copy of the DAgger behaviour
policy ``TensorDictSequential(expert, learner, BetaMixer)``, so the expert labels every
state in the worker. Before each round the driver sends the round's weights (the
learner's parameters and the mixer's ``beta`` buffer) once to every worker through
``RayCollector.update_policy_weights_`` (TorchRL's ``RayWeightSyncScheme``).

**Slots, seeds, order.** A round of ``n`` episodes is split into ``workers`` slots
(slot ``w`` plays ``ceil((n - w) / workers)`` episodes, as lanes do in
:func:`~imitrl.runtime.rollout_episodes`). A slot is one Ray call: the worker seeds its
env and its torch RNG (the learner's sampling and the mixer's coins) from
``SeedSequence([seed, 0, round, w])``, resets, and plays its whole episodes. Episode
ids are ``first_episode + (episodes of slots < w) + j``, so rows come in (round,
worker slot, episode) order and depend on ``(seed, workers)`` only, not on which actor
ran a slot, nor on what it ran before.

**An error in a worker** (its env or the policy raises) comes back as a value and is
raised in the driver with the worker's message and traceback, as the same builtin
exception type: a round that fails adds no rows. **A worker that dies** (its actor
process exits) loses its slot's call; the driver
gives that slot, with the same seeds, to a surviving worker, so the round completes
with the rows an undisturbed run gives (later rounds run on the survivors, with the
same slots). Rows reach the driver only as a slot's whole episodes, and the round is
returned only when every slot is in: nothing partial reaches the buffer. If every
worker has died the round raises ``RuntimeError`` and the buffer is left untouched.

**Why TorchRL's pieces and not its iterator.** ``RayCollector`` builds the actors,
places them (``remote_configs``) and broadcasts weights; each actor's inner
``Collector`` assembles whole episodes (``trajs_per_batch=1, traj_format="cat"``: only
trajectories ending in ``done`` are yielded). Its own iterator is not used: it runs
every worker for a fixed frame budget with no per-round seeding, and a dead worker
makes ``ray.get`` raise inside it, after which ``BaseCollector.__iter__`` shuts every
actor down, losing the other workers' finished episodes. So each slot is a call of
:meth:`EpisodeCollector.play_episodes` (a ``Collector`` subclass, TorchRL's
``collector_class`` extension point) on ``RayCollector.remote_collectors``, awaited
with ``ray.wait``.

**Why the driver's buffer and not a Ray-owned one.** DAgger refits on the whole
buffer in the driver after every round, so every row travels to the driver anyway;
a Ray-owned buffer (``ReplayBuffer(service_backend="ray")``, which ``RayCollector``
requires when given a buffer) would add a hop and could not keep the
(round, worker, episode) order nor refuse a dead worker's partial episodes. A round's
rows are small next to the refit (a few thousand rows per round in the benchmarks).

**Devices and threads.** Workers act on the CPU with one Ray CPU and one torch thread
each (:data:`WORKER_THREADS`); the learner trains wherever it lives: the workers' policy
(:func:`worker_policy`) and each round's weights are CPU copies of the driver's.

Ray is an optional dependency (``pip install 'imitrl[distributed]'``), imported when a
source starts. A source not given an ``address`` starts a local Ray instance with
``num_cpus=workers`` (and shuts it down in :meth:`RaySource.close`) unless Ray is
already running in this process; workers import imitrl and the user's modules through
``PYTHONPATH`` set to this process's ``sys.path`` (or ``runtime_env``).
"""

from __future__ import annotations

import time
import typing
import warnings
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, exploration_type

from imitrl import keys
from imitrl.algorithms.ray_setup import (
    RAY_INSTALL_HINT,
    WORKER_THREADS,
    import_ray,
    init_ray,
    patient_weight_sync,
)
from imitrl.algorithms.ray_worker import (
    EpisodeCollector,
    WorkerFailure,
    worker_env,
    worker_policy,
)
from imitrl.envs.limits import episode_limit
from imitrl.learners.learner import Learner
from imitrl.policies.experts import Expert
from imitrl.policies.mixture import BetaMixer, behaviour_policy
from imitrl.runtime.returns import EpisodeSummary

__all__ = [
    "RAY_INSTALL_HINT",
    "WORKER_THREADS",
    "RaySource",
    "RoundTiming",
    "WorkerFailure",
    "init_ray",
    "slot_seeds",
    "worker_env",
    "worker_policy",
]

COLLECT, EVALUATE = 0, 1
"""the seed streams of :func:`slot_seeds`"""


def slot_seeds(seed: int, stream: int, index: int, slot: int) -> tuple[int, int]:
    """(env seed, torch seed) of worker slot ``slot`` in round ``index`` of ``stream``.

    ``stream`` is ``COLLECT`` (``index`` = DAgger round) or ``EVALUATE``. Derived by
    numpy's ``SeedSequence([seed, stream, index, slot])``: distinct streams for every
    slot, round and purpose.
    """
    state = np.random.SeedSequence([int(seed), stream, int(index), int(slot)]).generate_state(2)
    return int(state[0]), int(state[1])


@dataclass
class RoundTiming:
    """Where the last round's (or evaluation's) wall time went, in seconds."""

    broadcast_s: float
    """liveness check and weight broadcast to every live worker"""
    play_s: float
    """the slowest slot, as measured inside its worker"""
    total_s: float
    """the whole call in the driver; ``total - broadcast - play`` is dispatch + gather"""


@dataclass
class RaySource:
    """Episodes of a behaviour policy played on ``workers`` Ray workers (module docstring).

    Attributes:
        make_env: picklable ``() -> EnvBase`` (e.g. ``functools.partial(make_env, id,
            seed=0)``), called once in the driver (specs, time limit) and once per worker.
        workers: Ray workers, and slots per round (the rows depend on it).
        seed: seeds every slot's env and torch RNG (:func:`slot_seeds`).
        address: an existing Ray cluster (``"auto"``, ``"ray://host:10001"``); None: a
            local Ray instance with ``num_cpus=workers`` (if Ray is not running yet).
        exploration: how the learner acts; None = as ``dagger`` says (``learner.exploration``).
        max_steps: most steps one episode may take where the env has no time limit of
            its own (episodes are truncated there by TorchRL's ``max_frames_per_traj``);
            None: the env's own limit, refused when it has none.
        frames_per_batch: env steps a worker takes between checks for finished
            episodes; at most ``frames_per_batch - 1`` steps per slot are played past its
            last episode and dropped.
        runtime_env: Ray ``runtime_env`` when this source starts Ray (see :func:`init_ray`).
    """

    make_env: Callable[[], EnvBase]
    workers: int
    seed: int = 0
    address: str | None = None
    exploration: ExplorationType | None = None
    max_steps: int | None = None
    frames_per_batch: int = 16
    runtime_env: dict | None = None
    startup: dict[str, float] = field(default_factory=dict, init=False)
    """seconds of ``ray_init``, ``actors`` (building the collectors), ``first_weights``"""
    last_timing: RoundTiming | None = field(default=None, init=False)
    _env: EnvBase = field(init=False, repr=False)
    _collector: typing.Any = field(
        default=None, init=False, repr=False
    )  # a RayCollector, once started
    _weight_keys: set = field(default_factory=set, init=False, repr=False)
    _alive: list[int] = field(default_factory=list, init=False, repr=False)
    _owns_ray: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        if int(self.workers) != self.workers or self.workers < 1:
            raise ValueError(f"workers must be a positive integer, got {self.workers!r}")
        if int(self.frames_per_batch) != self.frames_per_batch or self.frames_per_batch < 1:
            raise ValueError(f"frames_per_batch must be >= 1, got {self.frames_per_batch!r}")
        if self.max_steps is not None and (
            int(self.max_steps) != self.max_steps or self.max_steps < 1
        ):
            raise ValueError(
                f"max_steps must be a positive integer or None, got {self.max_steps!r}"
            )
        if not callable(self.make_env):
            raise ValueError(f"make_env must be a callable () -> EnvBase, got {self.make_env!r}")
        import_ray()  # fail before any work without the extra
        self._env = self.make_env()
        if self.max_steps is None and episode_limit(self._env) is None:
            self._env.close()
            raise ValueError(
                f"{type(self._env).__name__} has no time limit of its own: pass "
                "RaySource(..., max_steps=...) (the most steps one episode may take)"
            )

    @property
    def live_workers(self) -> int:
        """Workers still alive (``workers`` until the first round and until one dies)."""
        return len(self._alive) if self._collector is not None else int(self.workers)

    # -- the EpisodeSource protocol ---------------------------------------------------

    def check(self, expert: Expert, learner: Learner) -> None:
        """Bind ``expert`` to the env's action spec; refuse a ``learner`` that does not fit."""
        expert.bind(self._env.action_spec_unbatched)
        learner.check_env(self._env)

    def state_dict(self) -> dict:
        """Every draw is a function of ``(seed, round, slot)``: only those need to match."""
        return {"seed": int(self.seed), "workers": int(self.workers)}

    def load_state_dict(self, state: dict) -> None:
        """Refuse to resume a run collected with another seed or worker count."""
        if state != self.state_dict():
            raise ValueError(
                f"the run was collected by a RaySource with {state}, this one has "
                f"{self.state_dict()}: the rows would differ"
            )

    def collect(
        self,
        behaviour: TensorDictModuleBase,
        num_episodes: int,
        *,
        round_index: int,
        first_episode: int,
    ) -> TensorDict:
        """``num_episodes`` whole episodes of ``behaviour`` as buffer rows, in (slot, episode) order.

        Rows as :func:`~imitrl.runtime.rollout_episodes` gives them (``ROUND`` =
        ``round_index``, ``EPISODE`` from ``first_episode``, ``STEP``).
        """
        exploration = self.exploration or exploration_type()
        if exploration is None:
            raise ValueError(
                "exploration is not set: pass RaySource(exploration=...) or collect under "
                "torchrl's set_exploration_type (dagger does, with learner.exploration)"
            )
        seeds = [slot_seeds(self.seed, COLLECT, round_index, w) for w in range(self.workers)]
        slots = self._run(behaviour, num_episodes, seeds, exploration)
        counts = _quota(num_episodes, self.workers)
        rows, first = [], int(first_episode)
        for w, traj in slots.items():
            rows.append(_episode_rows(traj, counts[w], first_episode=first, slot=w))
            first += counts[w]
        out = TensorDict.cat(rows)
        out.set(keys.ROUND, torch.full((out.shape[0],), int(round_index), dtype=torch.int64))
        return out

    # -- evaluation on the same workers -----------------------------------------------

    def evaluate(
        self,
        expert: Expert,
        learner: Learner,
        num_episodes: int,
        *,
        seed: int,
        exploration: ExplorationType | None = None,
    ) -> EpisodeSummary:
        """Returns and lengths of ``num_episodes`` episodes of ``learner`` on the workers.

        The behaviour policy with ``beta = 0`` (the learner acts; the expert's labels are
        computed and dropped), slots seeded from ``seed`` apart from the collection
        rounds; ``exploration`` None: ``learner.exploration``. Episode ``j`` is the
        ``j``-th in (slot, episode) order. The workers then hold the learner's weights.
        """
        behaviour = behaviour_policy(expert, learner.policy, BetaMixer(0.0))
        seeds = [slot_seeds(seed, EVALUATE, 0, w) for w in range(self.workers)]
        slots = self._run(behaviour, num_episodes, seeds, exploration or learner.exploration)
        returns, lengths = [], []
        for traj in slots.values():
            done = traj.get((keys.NEXT, keys.DONE)).reshape(-1)
            episode = done.long().cumsum(0) - done.long()
            reward = traj.get((keys.NEXT, keys.REWARD)).reshape(-1).double()
            returns.append(
                torch.zeros(int(done.sum()), dtype=torch.float64).index_add_(0, episode, reward)
            )
            lengths.append(torch.bincount(episode))
        return EpisodeSummary(returns=torch.cat(returns), lengths=torch.cat(lengths), success=None)

    # -- the workers ------------------------------------------------------------------

    def _run(self, behaviour, num_episodes, seeds, exploration) -> dict[int, TensorDict]:
        """Broadcast ``behaviour``'s weights, play every slot (re-run where a worker died)."""
        if int(num_episodes) != num_episodes or num_episodes < 1:
            raise ValueError(f"num_episodes must be a positive integer, got {num_episodes!r}")
        if not isinstance(behaviour, TensorDictModuleBase):
            raise ValueError(
                f"behaviour must be a TensorDict module, got {type(behaviour).__name__}"
            )
        if self._collector is None:
            self._start(behaviour, exploration)
        start = time.perf_counter()
        broadcast = self._broadcast(behaviour)
        counts = _quota(int(num_episodes), self.workers)
        tasks = [(w, *seeds[w], counts[w]) for w in range(self.workers) if counts[w] > 0]
        slots, play = self._play(tasks, exploration)
        self.last_timing = RoundTiming(broadcast, play, time.perf_counter() - start)
        return dict(sorted(slots.items()))

    def _play(self, tasks, exploration) -> tuple[dict[int, TensorDict], float]:
        """Each task ``(slot, env_seed, torch_seed, n)`` on a free live worker; a dead one's
        slot goes back to the queue. Returns the slots' episodes and the slowest slot's time."""
        ray = import_ray()
        actors = self._collector.remote_collectors
        queue, free = deque(tasks), list(self._alive)
        pending: dict[typing.Any, tuple[int, tuple]] = {}  # a Ray reference -> (worker, task)
        slots: dict[int, TensorDict] = {}
        slowest = 0.0
        while queue or pending:
            while queue and free:
                actor, task = free.pop(0), queue.popleft()
                ref = actors[actor].play_episodes.remote(*task[1:], exploration)
                pending[ref] = (actor, task)
            if not pending:
                raise RuntimeError(
                    f"all {self.workers} Ray workers have died; slots {[t[0] for t in queue]} "
                    "of this round were not played and none of its rows reached the buffer"
                )
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            actor, task = pending.pop(ref)
            try:
                rows, seconds = ray.get(ref)
            except ray.exceptions.RayActorError as err:
                self._alive.remove(actor)
                queue.appendleft(task)
                warnings.warn(
                    f"Ray worker {actor} died ({type(err).__name__}); its slot {task[0]} is "
                    f"replayed on the {len(self._alive)} remaining workers",
                    RuntimeWarning,
                    stacklevel=3,
                )
                continue
            if isinstance(rows, WorkerFailure):  # nothing of the round reaches the buffer
                raise rows.error(task[0])
            slots[task[0]], slowest = rows, max(slowest, seconds)
            free.append(actor)
        return slots, slowest

    def _broadcast(self, behaviour: TensorDictModuleBase) -> float:
        """Send ``behaviour``'s weights to every live worker; returns the seconds it took."""
        start = time.perf_counter()
        weights = TensorDict.from_module(behaviour).data.cpu()  # the workers' copy is on the CPU
        if set(weights.keys(True, True)) != self._weight_keys:
            raise ValueError(
                "the behaviour policy's parameters differ from those the workers were built "
                "with: RaySource needs make_learner to build the same network every round"
            )
        self._drop_dead()
        self._collector.update_policy_weights_(weights, worker_ids=list(self._alive))
        seconds = time.perf_counter() - start
        self.startup.setdefault("first_weights", seconds)  # sets up the process group
        return seconds

    def _start(self, behaviour: TensorDictModuleBase, exploration) -> None:
        """``ray.init`` (unless running) and one ``EpisodeCollector`` actor per worker."""
        from torchrl.collectors.distributed import RayCollector

        patient_weight_sync()
        start = time.perf_counter()
        self._owns_ray = init_ray(self.workers, address=self.address, runtime_env=self.runtime_env)
        self.startup["ray_init"] = time.perf_counter() - start
        policy = worker_policy(behaviour)
        start = time.perf_counter()
        self._collector = RayCollector(
            worker_env(self.make_env, self._env, policy),
            policy,
            collector_class=EpisodeCollector,
            num_collectors=self.workers,
            frames_per_batch=int(self.frames_per_batch),
            total_frames=-1,
            max_frames_per_traj=self.max_steps,
            exploration_type=exploration,
            trust_policy=True,
            trajs_per_batch=1,
            collector_kwargs={"traj_format": "cat", "auto_register_policy_transforms": False},
            remote_configs={"num_cpus": WORKER_THREADS, "num_gpus": 0},
            sync=False,
        )
        self._alive = list(range(self.workers))
        self._weight_keys = set(TensorDict.from_module(policy).keys(True, True))
        self.startup["actors"] = time.perf_counter() - start

    def _drop_dead(self) -> None:
        """Forget workers that died since the last round (one ping each, in parallel)."""
        ray = import_ray()
        actors = self._collector.remote_collectors
        pings = {a: actors[a].__ray_ready__.remote() for a in self._alive}
        for actor, ref in pings.items():
            try:
                ray.get(ref)
            except ray.exceptions.RayActorError:
                self._alive.remove(actor)
        if not self._alive:
            raise RuntimeError(f"all {self.workers} Ray workers have died")

    def close(self) -> None:
        """Stop the workers, and Ray where this source started it."""
        if self._collector is not None:
            self._collector.shutdown()
            self._collector = None
        if self._owns_ray:
            import_ray().shutdown()
            self._owns_ray = False
        self._env.close()

    def __enter__(self) -> RaySource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _quota(num_episodes: int, slots: int) -> list[int]:
    """Episodes of slot ``w``: ``ceil((n - w) / slots)`` (round-robin counts)."""
    return [max(0, (num_episodes - w + slots - 1) // slots) for w in range(slots)]


def _episode_rows(traj: TensorDictBase, count: int, *, first_episode: int, slot: int) -> TensorDict:
    """A slot's ``count`` whole episodes ``[T]`` with ``EPISODE`` and ``STEP`` written."""
    done = traj.get((keys.NEXT, keys.DONE)).reshape(-1)
    ends = done.nonzero().squeeze(-1)
    if ends.numel() != count or not bool(done[-1]):
        raise RuntimeError(
            f"worker slot {slot} returned {ends.numel()} finished episodes for {count} "
            "(a partial episode): refusing to add its rows"
        )
    lengths = torch.diff(ends, prepend=torch.tensor([-1])).long()
    starts = torch.repeat_interleave(ends + 1 - lengths, lengths)
    rows = traj.clone()
    rows.set(keys.EPISODE, first_episode + torch.repeat_interleave(torch.arange(count), lengths))
    rows.set(keys.STEP, torch.arange(done.numel()) - starts)
    return rows

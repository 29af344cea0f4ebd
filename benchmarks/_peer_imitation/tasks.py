"""The three tasks of ``peer_imitation.py``: the same budgets on both sides.

A task travels to each child process as JSON (:meth:`Task.spec`): the imitrl child and
the peer's child read the same numbers, so the two sides cannot drift apart. Standard
library only.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

PROTOCOLS = ("own", "matched")
"""``own``: each library's defaults (imitrl refits a fresh learner every round with beta 0;
imitation trains one policy on with ``LinearBetaSchedule(15)``); ``matched``: both train
one policy on (imitrl ``warm_start=True``) with beta 0 (imitation ``beta_schedule=0``)"""
PROCESSES = ("plain", "collector_trick")
"""how an imitrl child runs its process (the spec's ``process``): ``plain``, as a user's
Python script runs (the garbage collector as Python starts it, nothing else touched);
``collector_trick``, as the ``imitrl`` command runs its own process
(:mod:`imitrl.system.heap`): the imports with the collector paused, then the import-time
heap frozen out of its walks (``freeze_imported``), then the collector on again. The
peer's children are always plain scripts"""
PROCESS_LABELS = {
    "plain": "plain script",
    "collector_trick": "collector trick",
    "command": "command as shipped",
}
"""each process kind as the reports name it (``command``: the shipped ``imitrl gail`` /
``imitrl airl`` command, ``peer_gail.py`` only)"""
EVAL_LANES = {"imitrl": 16, "imitation": 50}
"""vector envs each library evaluates on, as its own code does (imitrl's jobs: at most 16
lanes; imitation's scripts: 50)"""
EVAL_SEED = 10_000
"""evaluation env seed of training seed s: ``EVAL_SEED + s`` (every policy of a run
starts its evaluation episodes from the same reset seed; each library seeds its own
vector envs from it, so the two sample different initial states)"""


@dataclass(frozen=True)
class Task:
    """One task's demonstrations, DAgger rounds, fits and evaluation (both libraries)."""

    name: str
    """short name used in tables and results"""
    env_id: str
    """gymnasium id (FrozenLake-v1 is slippery 4x4 by default)"""
    demo_episodes: int
    """expert episodes demonstrated before BC"""
    demo_steps: int | None
    """keep only the first steps of the demonstrations (None: whole episodes)"""
    rounds: int
    """DAgger relabel rounds, each followed by a fit on everything collected"""
    episodes_per_round: int
    """episodes played by the behaviour policy and labelled by the expert per round"""
    bc_steps: int
    """gradient steps of the BC fit on the demonstrations"""
    round_steps: int
    """gradient steps of the fit after each relabel round"""
    batch_size: int
    """rows per gradient step"""
    eval_episodes: int
    """evaluation episodes per evaluated policy (the BC learner and the final one)"""
    hidden: tuple[int, ...] = (32, 32)
    """hidden layers of the tanh MLP (imitation's default ``FeedForward32Policy``)"""

    def spec(
        self,
        seed: int,
        protocol: str = "own",
        imitrl_loss: str = "default",
        process: str = "plain",
    ) -> dict:
        """What a child process reads: the task, the training and evaluation seeds, the
        protocol, each library's evaluation lanes, imitrl's learner (``default``: the
        one ``build("for_env", env)`` builds, ``--loss for_env``; else a loss-registry
        name) and how imitrl's child runs its process (:data:`PROCESSES`)."""
        if protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
        check_process(process)
        return {
            **asdict(self),
            "hidden": list(self.hidden),
            "seed": seed,
            "eval_seed": EVAL_SEED + seed,
            "protocol": protocol,
            "eval_lanes": dict(EVAL_LANES),
            "imitrl_loss": imitrl_loss,
            "process": process,
        }


def check_process(process: str) -> str:
    """``process`` if it is one of :data:`PROCESSES`, else ``ValueError``."""
    if process not in PROCESSES:
        raise ValueError(f"process must be one of {PROCESSES}, got {process!r}")
    return process


TASKS: dict[str, Task] = {
    t.name: t
    for t in (
        Task("frozenlake", "FrozenLake-v1", 3, None, 4, 3, 1000, 500, 32, 1000),
        Task("cartpole", "CartPole-v1", 1, 25, 5, 2, 1000, 500, 25, 20),
        Task("pendulum", "Pendulum-v1", 1, None, 5, 2, 1000, 500, 32, 20),
    )
}
"""imitation's small setups as issue 16 states them (batch 25 on CartPole: imitation's
BC refuses a batch larger than its 25 demonstrated rows)"""


def quick(task: Task) -> Task:
    """The smoke budget: one relabel round of one episode, tiny fits, two evaluation episodes."""
    return replace(
        task,
        rounds=1,
        episodes_per_round=1,
        bc_steps=20,
        round_steps=10,
        eval_episodes=2,
    )

"""The GAIL and AIRL tasks of ``peer_gail.py`` and each side's settings under each protocol.

Standard library only: both children (imitrl's, and imitation's in the peer's venv) read
the settings resolved here from the JSON spec, so the two sides cannot drift apart.

Two protocols, named beside every ratio:

* ``own``: each library at its own recommended settings. imitation: its GAIL tutorial
  (``docs/tutorials/3_train_gail``: PPO ``batch_size=64, n_epochs=5, ent_coef=0``,
  learning rate 4e-4, gamma 0.95; ``BasicRewardNet`` with ``RunningNorm``;
  ``demo_batch_size=1024, gen_replay_buffer_capacity=512, n_disc_updates_per_round=8``).
  imitrl: ``GAILConfig``'s defaults (PPO 10 epochs of minibatches of 256, 10
  discriminator steps of 256 + 256 transitions, learning rates 3e-4, gamma 0.99);
* ``matched``: imitrl with imitation's numbers wherever both have the knob (learning
  rate, gamma, PPO epochs and minibatch, discriminator steps, batch, learning rate (Adam's
  default 1e-3 in imitation) and hidden layers (``BasicRewardNet``'s 32, 32)). imitation
  runs the same in both protocols, so it runs once per (task, seed).

AIRL (tasks ``*_airl``) likewise: imitation's AIRL tutorial (``docs/tutorials/4_train_airl``:
PPO ``batch_size=64, n_epochs=5, ent_coef=0, clip_range=0.1, vf_coef=0.1``, learning rate
5e-4, gamma 0.95; ``BasicShapedRewardNet`` with ``RunningNorm``; ``demo_batch_size=2048,
gen_replay_buffer_capacity=512, n_disc_updates_per_round=16``) against ``imitrl airl``'s
defaults (``AIRLConfig``: GAIL's, and the generator paid ``f - log pi``), with the
generator's entropy weight the task's where imitrl recommends one (Pendulum: 0, measured
in ``beyond_cloning.py``); ``matched`` also gives imitrl imitation's PPO clip (imitrl has
no value-loss coefficient to set). imitation's ``demo_batch_size`` must not exceed the
demonstrations' transitions, so Pendulum's AIRL task takes 11 episodes (2,200 rows).

On both sides and in both protocols: ``lanes`` envs stepped together (the tutorial's 8),
``rollout_steps`` env steps per round (imitation: PPO ``n_steps = rollout_steps /
lanes``), ``total_steps`` in all, ``demo_episodes`` greedy expert episodes, a greedy
evaluation of ``eval_episodes`` episodes on ``eval_lanes`` vector envs seeded
``eval_seed`` (as each library's own scripts evaluate). Where a task sets ``lr`` or
``gamma`` (Pendulum: 1e-3 and 0.9, untuned defaults fail there on both sides) both
libraries use it in both protocols.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from _peer_imitation.tasks import check_process

EVAL_SEED = 10_000
PROTOCOLS = ("own", "matched")
LEARNER_HIDDEN = (64, 64)
"""imitrl's learner's hidden layers (``imitrl gail``'s default MLP), script and command"""

IMITATION = {
    "lr": 4e-4, "gamma": 0.95, "ppo_epochs": 5, "minibatch_size": 64,
    "discriminator_updates": 8, "discriminator_batch": 1024, "discriminator_lr": 1e-3,
    "discriminator_hidden": [32, 32], "gen_replay_buffer_capacity": 512,
}  # fmt: skip
"""imitation's GAIL tutorial (and its defaults where the tutorial is silent)"""
IMITRL = {
    "lr": 3e-4, "gamma": 0.99, "ppo_epochs": 10, "minibatch_size": 256,
    "discriminator_updates": 10, "discriminator_batch": 256, "discriminator_lr": 3e-4,
    "discriminator_hidden": [64, 64],
}  # fmt: skip
"""imitrl's defaults (``GAILConfig``, ``ActorCritic``'s learning rate for PPO)"""
IMITATION_AIRL = {
    "lr": 5e-4, "gamma": 0.95, "ppo_epochs": 5, "minibatch_size": 64, "clip_epsilon": 0.1,
    "vf_coef": 0.1, "discriminator_updates": 16, "discriminator_batch": 2048,
    "discriminator_lr": 1e-3, "discriminator_hidden": [32, 32],
    "gen_replay_buffer_capacity": 512,
}  # fmt: skip
"""imitation's AIRL tutorial (and its defaults where the tutorial is silent)"""
IMITRL_AIRL = {**IMITRL, "clip_epsilon": 0.2, "entropy_weight": 1.0}
"""imitrl's defaults (``AIRLConfig``; PPO's clip and the generator's entropy weight)"""


@dataclass(frozen=True)
class GailTask:
    name: str
    env_id: str
    total_steps: int
    lr: float | None = None
    """both libraries' learning rate (None: each its own)"""
    gamma: float | None = None
    """both libraries' discount (None: each its own)"""
    method: str = "gail"
    """``gail`` or ``airl``"""
    entropy_weight: float | None = None
    """imitrl's AIRL generator's entropy weight on this task (None: its default)"""
    demo_episodes: int = 10
    rollout_steps: int = 2048
    lanes: int = 8
    eval_episodes: int = 20
    eval_lanes: int = 10

    def spec(self, seed: int, library: str, protocol: str, process: str = "plain") -> dict:
        """What a child reads: the task, seeds, the resolved settings of its side and how
        imitrl's child runs its process (``tasks.PROCESSES``; the peer's ignores it)."""
        return {
            **asdict(self),
            "seed": seed,
            "eval_seed": EVAL_SEED + seed,
            "protocol": protocol,
            "settings": settings(self, library, protocol),
            "learner_hidden": list(LEARNER_HIDDEN),
            "process": check_process(process),
        }


def settings(task: GailTask, library: str, protocol: str) -> dict:
    """The hyperparameters ``library`` runs ``task`` with under ``protocol``."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    theirs, ours = (IMITATION_AIRL, IMITRL_AIRL) if task.method == "airl" else (IMITATION, IMITRL)
    out = dict(theirs if library == "imitation" or protocol == "matched" else ours)
    if task.method == "airl" and library == "imitrl":  # a knob imitation does not have
        out["entropy_weight"] = (
            IMITRL_AIRL["entropy_weight"] if task.entropy_weight is None else task.entropy_weight
        )
    if task.lr is not None:
        out["lr"] = task.lr
    if task.gamma is not None:
        out["gamma"] = task.gamma
    return out


def command_flags(task: GailTask, seed: int, out: str) -> list[str]:
    """The arguments of the shipped ``imitrl gail`` (``imitrl airl``) that run ``task``'s
    seed as imitrl's ``own``-protocol script does: the same env, lanes, budget, rounds,
    demonstrations, learner layers and every hyperparameter of :func:`settings` (the
    command's defaults, given explicitly so that the two cannot drift apart), the same
    evaluation episodes and seed, CPU, 1 thread, no progress bars; ``--eval-every 0``
    evaluates the learner after the last round only, as the script does. What the command
    adds is its own: the expert's and the untrained learner's evaluations, the CSV
    logger, results.json, the checkpoint and curves.png in ``out``, and its evaluations
    on ``min(episodes, 16)`` lanes (``imitrl.jobs.evaluate.EVAL_LANES``)."""
    s = settings(task, "imitrl", "own")
    flags: dict[str, object] = {
        "env": task.env_id, "num-envs": task.lanes, "total-steps": task.total_steps,
        "rollout-steps": task.rollout_steps, "demos": task.demo_episodes,
        "hidden": _widths(LEARNER_HIDDEN), "lr": s["lr"], "gamma": s["gamma"],
        "ppo-epochs": s["ppo_epochs"], "minibatch-size": s["minibatch_size"],
        "discriminator-updates": s["discriminator_updates"],
        "discriminator-batch": s["discriminator_batch"],
        "discriminator-lr": s["discriminator_lr"],
        "discriminator-hidden": _widths(s["discriminator_hidden"]),
    }  # fmt: skip
    if task.method == "airl":
        flags["clip-epsilon"] = s["clip_epsilon"]
        flags["entropy-weight"] = s["entropy_weight"]
    flags.update({
        "eval-episodes": task.eval_episodes, "eval-seed": EVAL_SEED + seed, "eval-every": 0,
        "seed": seed, "device": "cpu", "threads": 1, "out": out,
    })  # fmt: skip
    return [
        task.method,
        *(a for k, v in flags.items() for a in (f"--{k}", str(v))),
        "--no-progress",
    ]


def _widths(layers) -> str:
    return ",".join(str(w) for w in layers)


TASKS = {
    t.name: t
    for t in (
        GailTask("cartpole", "CartPole-v1", 24_576),
        GailTask("pendulum", "Pendulum-v1", 30_720, lr=1e-3, gamma=0.9),
        GailTask("cartpole_airl", "CartPole-v1", 24_576, method="airl"),
        GailTask(
            "pendulum_airl",
            "Pendulum-v1",
            30_720,
            lr=1e-3,
            gamma=0.9,
            method="airl",
            entropy_weight=0.0,
            demo_episodes=11,
        ),
    )
}
"""issue 31's budgets: 12 and 15 rounds of 2048 steps, the same for GAIL and AIRL"""


def quick(task: GailTask) -> GailTask:
    """The smoke budget: two rounds of 64 steps on 2 lanes, 2 evaluation episodes."""
    return replace(
        task, total_steps=128, rollout_steps=64, lanes=2, demo_episodes=1, eval_episodes=2,
        eval_lanes=2,
    )  # fmt: skip

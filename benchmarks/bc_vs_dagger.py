"""BC vs DAgger with neural policies, discrete and continuous, on the library's pipeline.

For each env and seed (same code path for every env; nothing below branches on the env):

1. one expert demonstration (CartPole-v1: cut to its first 25 steps, since a full
   500-step episode already clones perfectly) goes into a ``DemonstrationBuffer``;
2. ``dagger`` fits a fresh MLP on the buffer (round 0 = BC on the demonstration),
   then runs ``relabel_rounds`` rounds of: roll the learner (beta = 0), label every
   visited state with the expert, aggregate, refit;
3. "BC, matched": a fresh MLP fitted on as many expert-driven rows as DAgger's final
   buffer holds (the first N rows of fresh expert episodes);
4. every learner, the expert and a uniformly random policy are evaluated greedily on
   the same ``eval_episodes`` initial states (the eval env is re-seeded before each).

The learners are ``ActorCritic.for_env`` MLPs with the library's defaults, observations
normalised by the demonstrations' statistics included. Scores are normalised per seed:
``(R - R_random) / (R_expert - R_random)`` with ``R_expert`` and ``R_random`` the
expert's and the random policy's mean returns on the seed's evaluation states.
"Reached" means a DAgger round 1..5 scored at least ``threshold`` (0.95). The expert
table measures each expert and the random policy over ``reference_episodes`` (100)
episodes from the same initial states: every built-in expert, or the ``--env`` ones.
Intervals are 95% Student-t over seeds.

    python benchmarks/bc_vs_dagger.py            # full run, refreshes benchmarks/README.md
    python benchmarks/bc_vs_dagger.py --quick    # smoke run, into a temporary directory
    python benchmarks/bc_vs_dagger.py --parallel # DAgger rollouts in worker processes
    python benchmarks/bc_vs_dagger.py --env Pendulum-v1 --env CartPole-v1 --out /tmp/x
    PYTHONPATH=examples python benchmarks/bc_vs_dagger.py --out /tmp/x \\
        --env MountainCarContinuous-v0 --expert mypkg.experts:mountain_car

``--env`` takes a gymnasium id (or ``module:Env-v0``, imported first); ``--expert``
takes ``module:function``, an expert builder or a batched ``obs -> action`` callable,
for an env without a built-in expert.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

import _report
from _bc_vs_dagger_report import figure, markdown
from _common import (
    BUILT_IN_EXPERTS,
    DET,
    expert_for,
    reference_returns,
    returns,
    rollout,
    source,
    time_limit,
)
from imitrl.algorithms import BCConfig, Constant, DAggerConfig, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.evaluation import t_interval
from imitrl.experts import (
    cartpole_expert,
    inverted_double_pendulum_expert,
    inverted_pendulum_expert,
    pendulum_expert,
)
from imitrl.learners import ActorCritic, build
from imitrl.policies import HEADS

NAME = "bc_vs_dagger"
EVAL_SEED, SOURCE_SEED, MATCHED_SEED, REFERENCE_SEED = 10_000, 1_000, 2_000, 50_000


@dataclass(frozen=True)
class Task:
    """One env of the study: its expert, the learner's head and loss, the DAgger budget."""

    env_id: str
    """gymnasium id (or ``module:Env-v0``), built by ``imitrl.envs.make_env``"""
    expert: Callable[[], TensorDictModuleBase]
    """builds the queryable expert"""
    head: str | None = None
    """ActorCritic head (None: categorical for discrete actions, else deterministic)"""
    loss: str | None = None
    """BC loss type of the head (None: its default, nll or mse)"""
    demo_steps: int | None = None
    """keep only the first steps of the one demonstration (None = the whole episode)"""
    episodes_per_round: int = 4
    """learner episodes relabelled per DAgger round (rolled in parallel lanes)"""
    fit_steps: int = 1000
    """Adam steps of every fit (minibatches of Config.batch_size)"""


TASKS = (
    Task("CartPole-v1", cartpole_expert, "categorical", "nll", 25, 2, 1000),
    Task("Pendulum-v1", pendulum_expert, "deterministic", "mse", None, 20, 2000),
    Task("InvertedPendulum-v5", inverted_pendulum_expert, "deterministic", "mse", None, 4, 1000),
    Task(
        "InvertedDoublePendulum-v5",
        inverted_double_pendulum_expert,
        "deterministic",
        "mse",
        None,
        4,
        1000,
    ),
)


@dataclass(frozen=True)
class Config:
    """The whole run."""

    seeds: int = 5
    """training seeds per env (seed s: demo env seed s, learner init seed s)"""
    relabel_rounds: int = 5
    """DAgger rounds after the BC fit"""
    eval_episodes: int = 50
    """greedy evaluation episodes per learner (one lane each, same initial states)"""
    reference_episodes: int = 100
    """episodes of the expert table (expert and uniform random, same initial states)"""
    batch_size: int = 256
    """minibatch of every fit"""
    lr: float = 1e-3
    """Adam learning rate"""
    hidden: tuple[int, ...] = (64, 64)
    """MLP hidden sizes"""
    threshold: float = 0.95
    """normalised score that counts as reaching the expert"""
    parallel: bool = False
    """collect DAgger rounds in worker processes (ParallelEnv) instead of in-process lanes"""
    max_episode_steps: int | None = None
    """override every env's time limit (the smoke run cuts episodes short)"""
    fit_steps: int | None = None
    """override every task's fit_steps (the smoke run)"""


QUICK = Config(
    seeds=1,
    relabel_rounds=1,
    eval_episodes=2,
    reference_episodes=2,
    max_episode_steps=30,
    fit_steps=5,
)


def horizon(env_id: str, cfg: Config) -> int:
    return cfg.max_episode_steps or time_limit(env_id)


def make_learner(env: EnvBase, task: Task, cfg: Config, seed: int) -> ActorCritic:
    """Fresh MLP for ``env``'s observation and action specs."""
    return build(
        "for_env", env, head=task.head, loss=task.loss, hidden=cfg.hidden, lr=cfg.lr, seed=seed
    )


def expert_table(experts: dict[str, Callable], cfg: Config) -> dict:
    """Expert and uniform-random returns over ``reference_episodes`` (one lane each)."""
    out = {}
    for env_id, make_expert in experts.items():
        n = cfg.reference_episodes
        env = make_env(
            env_id, seed=REFERENCE_SEED, num_envs=n, max_episode_steps=cfg.max_episode_steps
        )
        ref = reference_returns(
            env, make_expert(), n, seed=REFERENCE_SEED, max_steps=2 * horizon(env_id, cfg)
        )
        env.close()
        out[env_id] = {}
        for who, r in ref.items():
            mean, lo, hi = t_interval(r.tolist())
            out[env_id][who] = {"mean": mean, "ci": [lo, hi], "episodes": n}
    return out


def demonstration(task: Task, seed: int, cfg: Config) -> DemonstrationBuffer:
    """One expert episode (cut to ``demo_steps``) in a buffer."""
    env = make_env(task.env_id, seed=seed, max_episode_steps=cfg.max_episode_steps)
    limit = 4 * horizon(task.env_id, cfg)
    demo = rollout(env, task.expert().as_actor(), 1, exploration=DET, max_steps=limit)
    if task.demo_steps is not None:
        demo = demo[: task.demo_steps]
    buffer = DemonstrationBuffer(action_spec=env.action_spec)
    buffer.extend(demo)
    env.close()
    return buffer


def expert_rows(task: Task, seed: int, cfg: Config, n: int) -> TensorDict:
    """The first ``n`` rows of fresh expert episodes (``episodes_per_round`` lanes)."""
    env = make_env(
        task.env_id,
        seed=MATCHED_SEED + seed,
        num_envs=task.episodes_per_round,
        max_episode_steps=cfg.max_episode_steps,
    )
    limit = 4 * horizon(task.env_id, cfg)
    expert = task.expert().as_actor()
    chunks, have = [], 0
    while have < n:
        chunk = rollout(env, expert, task.episodes_per_round, exploration=DET, max_steps=limit)
        chunks.append(chunk)
        have += chunk.shape[0]
    env.close()
    return torch.cat(chunks)[:n]


def _normaliser(
    env_id: str, seed: int, expert_return: float, random_return: float, n: int, limit: int
) -> Callable[[float], float]:
    """A return as a share of the way from random actions' to the expert's (nan, said on
    stderr, where the two are equal)."""
    gap = expert_return - random_return
    if gap == 0:  # nothing to normalise by: say so instead of printing nan
        print(
            f"{env_id} seed {seed}: the expert and the random policy both return "
            f"{expert_return:.4g} over {n} episodes of at most {limit} steps, so normalised "
            "scores are undefined (nan); the episodes are too short for the expert to differ "
            "(give a larger --max-episode-steps)",
            file=sys.stderr,
        )

    def normalise(r: float) -> float:
        return (r - random_return) / gap if gap != 0 else float("nan")

    return normalise


def run_seed(task: Task, seed: int, cfg: Config) -> dict:
    """One training seed of one env: BC, DAgger per round, BC with matched samples."""
    limit = 4 * horizon(task.env_id, cfg)
    bc = BCConfig(num_steps=cfg.fit_steps or task.fit_steps, batch_size=cfg.batch_size, seed=seed)
    expert = task.expert()
    buffer = demonstration(task, seed, cfg)

    # -- evaluation on the same initial states for every policy of this seed
    n, eval_seed = cfg.eval_episodes, EVAL_SEED + seed
    eval_env = make_env(
        task.env_id, seed=eval_seed, num_envs=n, max_episode_steps=cfg.max_episode_steps
    )
    ref = reference_returns(eval_env, expert, n, seed=eval_seed, max_steps=limit)
    expert_return, random_return = float(ref["expert"].mean()), float(ref["random"].mean())

    def score(policy: TensorDictModuleBase) -> float:
        eval_env.set_seed(eval_seed)
        return float(returns(eval_env, policy, n, exploration=DET, max_steps=limit).mean())

    normalise = _normaliser(task.env_id, seed, expert_return, random_return, n, limit)

    # -- DAgger; its round 0 is BC on the demonstration
    source_env = make_env(
        task.env_id,
        seed=SOURCE_SEED + seed,
        num_envs=task.episodes_per_round,
        parallel=cfg.parallel,
        max_episode_steps=cfg.max_episode_steps,
    )
    learner_of = partial(make_learner, source_env, task, cfg, seed)
    dagger_returns: list[float] = []
    t0 = time.perf_counter()
    result = dagger(
        source(source_env, exploration=DET, max_steps=limit),
        expert,
        learner_of,
        buffer,
        DAggerConfig(
            rounds=cfg.relabel_rounds + 1,
            episodes_per_round=task.episodes_per_round,
            beta=Constant(0.0),
            bc=bc,
            seed=seed,
        ),
        on_fit=lambda k, learner: dagger_returns.append(score(learner.policy)),
    )
    dagger_s = time.perf_counter() - t0
    rows = [r.rows_trained for r in result.rounds]

    # -- BC with as many expert samples as DAgger's last fit used
    matched = learner_of()
    source_env.close()
    matched_rows = expert_rows(task, seed, cfg, rows[-1])
    fit_bc(matched, matched_rows, bc)
    matched_return = score(matched.policy)
    eval_env.close()

    scores = [normalise(r) for r in dagger_returns]
    reached = [k for k in range(1, len(scores)) if scores[k] >= cfg.threshold]
    return {
        "seed": seed,
        "expert_return": expert_return,
        "random_return": random_return,
        "dagger_returns": dagger_returns,
        "dagger_scores": scores,
        "rows": rows,
        "bc_return": dagger_returns[0],
        "bc_score": scores[0],
        "bc_matched_return": matched_return,
        "bc_matched_score": normalise(matched_return),
        "bc_matched_rows": int(matched_rows.shape[0]),
        "first_round_reached": reached[0] if reached else None,
        "dagger_seconds": dagger_s,
    }


def run(
    cfg: Config,
    tasks: tuple[Task, ...] = TASKS,
    experts: dict[str, Callable] | None = None,
    log=print,
) -> dict:
    """Every task's seeds, and the expert table of ``experts`` (default: the tasks' own)."""
    t_start = time.perf_counter()
    experts = experts if experts is not None else {t.env_id: t.expert for t in tasks}
    references = expert_table(experts, cfg)
    for env_id, ref in references.items():
        log(f"reference {env_id}: {ref}")
    out = {}
    for task in tasks:
        t0 = time.perf_counter()
        seeds = []
        for seed in range(cfg.seeds):
            record = run_seed(task, seed, cfg)
            seeds.append(record)
            log(
                f"{task.env_id} seed {seed}: bc {record['bc_score']:.2f} dagger "
                f"{[round(x, 2) for x in record['dagger_scores']]} matched "
                f"{record['bc_matched_score']:.2f} rows {record['rows']}"
            )
        fields = {f.name: getattr(task, f.name) for f in dataclasses.fields(task)}
        out[task.env_id] = {
            "task": {**fields, "expert": task.expert.__name__},
            "demo": (
                f"1 episode, first {task.demo_steps} steps"
                if task.demo_steps is not None
                else "1 episode"
            ),
            "seeds": seeds,
            "seconds": time.perf_counter() - t0,
        }
    return {
        "config": dataclasses.asdict(cfg),
        "references": references,
        "tasks": out,
        "seconds": time.perf_counter() - t_start,
    }


def tasks_from(
    env_ids: list[str] | None, expert: str | None, overrides: dict
) -> tuple[tuple[Task, ...], dict[str, Callable]]:
    """The tasks and the expert table named on the command line.

    No ``--env``: every task of ``TASKS``, and every built-in expert in the table. An
    ``--env`` of ``TASKS`` without ``--expert`` keeps its row; otherwise the env takes
    ``--expert`` (or its built-in expert) and the ``Task`` defaults. ``overrides``
    replace fields of every task.
    """
    if expert is not None and (not env_ids or len(env_ids) != 1):
        raise ValueError("--expert labels one env: give exactly one --env with it")
    if not env_ids:
        tasks = tuple(dataclasses.replace(t, **overrides) for t in TASKS)
        return tasks, dict(BUILT_IN_EXPERTS)
    rows = {t.env_id: t for t in TASKS}
    tasks = []
    for env_id in env_ids:
        if expert is None and env_id in rows:
            task = rows[env_id]
        else:
            task = Task(env_id, expert_for(env_id, expert))
        tasks.append(dataclasses.replace(task, **overrides))
    tasks = tuple(tasks)
    return tasks, {t.env_id: t.expert for t in tasks}


def main(argv: list[str] | None = None) -> dict:
    parser = _report.parser(__doc__)
    parser.add_argument("--seeds", type=int, default=None, help="training seeds per env")
    parser.add_argument("--parallel", action="store_true", help="ParallelEnv rollouts")
    parser.add_argument(
        "--env", action="append", default=None, metavar="ID", help="env id (repeatable)"
    )
    parser.add_argument("--expert", default=None, metavar="MODULE:FUNCTION")
    parser.add_argument("--head", default=None, choices=HEADS)
    parser.add_argument("--loss", default=None, help="loss type of the head (nll, mse, l1, ...)")
    parser.add_argument("--demo-steps", type=int, default=None)
    parser.add_argument("--episodes-per-round", type=int, default=None)
    parser.add_argument("--fit-steps", type=int, default=None)
    parser.add_argument(
        "--max-episode-steps", type=int, default=None,
        help="time limit of every env (default: each env's own; --quick: 30)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    knobs = ("head", "loss", "demo_steps", "episodes_per_round", "fit_steps")
    overrides = {k: getattr(args, k) for k in knobs if getattr(args, k) is not None}
    tasks, experts = tasks_from(args.env, args.expert, overrides)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    torch.set_num_threads(1)
    cfg = QUICK if args.quick else Config()
    if args.seeds is not None:
        cfg = dataclasses.replace(cfg, seeds=args.seeds)
    if args.parallel:
        cfg = dataclasses.replace(cfg, parallel=True)
    if args.max_episode_steps is not None:
        if args.max_episode_steps < 1:
            raise SystemExit(f"--max-episode-steps must be >= 1, got {args.max_episode_steps}")
        cfg = dataclasses.replace(cfg, max_episode_steps=args.max_episode_steps)
    results = run(cfg, tasks, experts, log=lambda s: print(s, file=sys.stderr, flush=True))
    results["machine"] = _report.machine()
    figure(results, cfg, _report.results_dir(out_dir) / f"{NAME}.png")
    _report.write(NAME, results, markdown(results, cfg), out_dir=out_dir)
    print(markdown(results, cfg))
    return results


if __name__ == "__main__":
    main()

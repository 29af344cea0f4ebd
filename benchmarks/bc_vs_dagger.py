"""BC vs DAgger with neural policies, discrete and continuous, on the library's pipeline.

For each env and seed (same code path for every env; nothing below branches on the env):

1. one expert demonstration (CartPole-v1: cut to its first 25 steps, since a full
   500-step episode already clones perfectly) goes into a ``DemonstrationBuffer``;
2. ``dagger`` fits a fresh MLP on the buffer (round 0 = BC on the demonstration),
   then runs ``relabel_rounds`` rounds of: roll the learner (beta = 0), label every
   visited state with the expert, aggregate, refit;
3. "BC, matched": a fresh MLP fitted on as many expert-driven rows as DAgger's final
   buffer holds (the first N rows of fresh expert episodes);
4. every learner, and the expert, is evaluated greedily on the same
   ``eval_episodes`` initial states (the eval env is re-seeded before each call).

Scores are normalised per seed: ``(R - R_random) / (R_expert - R_random)`` with
``R_expert`` the expert's mean return on the same initial states and ``R_random``
a uniform-random policy's mean over ``reference_episodes``. "Reached" means a
DAgger round 1..5 scored at least ``threshold`` (0.95). The expert table measures every
built-in expert over ``reference_episodes`` (100) episodes. Intervals are 95%
Student-t over seeds.

    python benchmarks/bc_vs_dagger.py            # full run, refreshes benchmarks/README.md
    python benchmarks/bc_vs_dagger.py --quick --out /tmp/smoke
    python benchmarks/bc_vs_dagger.py --parallel # DAgger rollouts in worker processes
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import gymnasium
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Categorical
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, RandomPolicy

import _report
from imitrl import keys
from imitrl.algorithms import BCConfig, Constant, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.data import DemonstrationBuffer, rollout_episodes
from imitrl.envs import make_env
from imitrl.evaluation import evaluate, t_interval
from imitrl.experts import (
    acrobot_expert,
    cartpole_expert,
    inverted_double_pendulum_expert,
    inverted_pendulum_expert,
    mountaincar_expert,
    pendulum_expert,
)
from imitrl.policies import ActorCritic

NAME = "bc_vs_dagger"
DET = ExplorationType.DETERMINISTIC
EVAL_SEED, SOURCE_SEED, MATCHED_SEED, REFERENCE_SEED = 10_000, 1_000, 2_000, 50_000


@dataclass(frozen=True)
class Task:
    """One env of the study: its expert, the learner's head and the DAgger budget."""

    env_id: str
    """gymnasium id, built by ``imitrl.envs.make_env``"""
    expert: Callable[[], TensorDictModuleBase]
    """builds the queryable expert"""
    head: str
    """ActorCritic.mlp head: categorical | tanh_normal | deterministic"""
    loss_type: str
    """BC loss: nll | mse | l1 | smooth_l1"""
    demo_steps: int | None
    """keep only the first steps of the one demonstration (None = the whole episode)"""
    episodes_per_round: int
    """learner episodes relabelled per DAgger round (rolled in parallel lanes)"""
    fit_steps: int
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
REFERENCE_EXPERTS = (
    ("CartPole-v1", cartpole_expert),
    ("MountainCar-v0", mountaincar_expert),
    ("Acrobot-v1", acrobot_expert),
    ("Pendulum-v1", pendulum_expert),
    ("InvertedPendulum-v5", inverted_pendulum_expert),
    ("InvertedDoublePendulum-v5", inverted_double_pendulum_expert),
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
    """episodes for the expert table and the random-policy baseline"""
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
    return cfg.max_episode_steps or gymnasium.spec(env_id).max_episode_steps


def make_learner(env: EnvBase, task: Task, cfg: Config, seed: int) -> ActorCritic:
    """Fresh MLP for ``env``'s spaces: categorical for integer actions, else bounded continuous."""
    spec = env.action_spec_unbatched
    action = int(spec.space.n) if isinstance(spec, Categorical) else spec
    obs_dim = env.observation_spec[keys.OBSERVATION].shape[-1]
    return ActorCritic.mlp(obs_dim, action, head=task.head, hidden=cfg.hidden, lr=cfg.lr, seed=seed)


def reference_returns(env_id: str, expert: TensorDictModuleBase, cfg: Config) -> dict:
    """Expert and uniform-random returns over ``reference_episodes`` (one lane each)."""
    n, limit = cfg.reference_episodes, 2 * horizon(env_id, cfg)
    env = make_env(env_id, seed=REFERENCE_SEED, num_envs=n, max_episode_steps=cfg.max_episode_steps)
    out = {}
    for name, policy in (
        ("expert", expert.as_actor()),
        ("random", RandomPolicy(env.action_spec)),
    ):
        env.set_seed(REFERENCE_SEED)
        torch.manual_seed(REFERENCE_SEED)  # RandomPolicy draws from the global RNG
        ev = evaluate(env, policy, n, exploration=DET, max_steps=limit)
        out[name] = {"mean": ev.mean_return, "ci": list(ev.return_ci), "episodes": n}
    env.close()
    return out


def run_seed(task: Task, seed: int, cfg: Config, random_return: float) -> dict:
    """One training seed of one env: BC, DAgger per round, BC with matched samples."""
    limit = 4 * horizon(task.env_id, cfg)
    fit = BCConfig(
        num_steps=cfg.fit_steps or task.fit_steps,
        batch_size=cfg.batch_size,
        loss_type=task.loss_type,
        seed=seed,
    )
    expert = task.expert()
    steps = cfg.max_episode_steps

    # -- the demonstration: one expert episode (cut for CartPole)
    demo_env = make_env(task.env_id, seed=seed, max_episode_steps=steps)
    demo = rollout_episodes(demo_env, expert.as_actor(), 1, exploration=DET, max_steps=limit)
    if task.demo_steps is not None:
        demo = demo[: task.demo_steps]
    buffer = DemonstrationBuffer(action_spec=demo_env.action_spec)
    buffer.extend(demo)

    # -- evaluation on the same initial states for every policy of this seed
    eval_env = make_env(
        task.env_id, seed=EVAL_SEED + seed, num_envs=cfg.eval_episodes, max_episode_steps=steps
    )

    def score(policy: TensorDictModuleBase) -> float:
        eval_env.set_seed(EVAL_SEED + seed)
        return evaluate(
            eval_env, policy, cfg.eval_episodes, exploration=DET, max_steps=limit
        ).mean_return

    expert_return = score(expert.as_actor())

    def normalise(r: float) -> float:
        gap = expert_return - random_return
        return (r - random_return) / gap if gap != 0 else float("nan")

    # -- DAgger; its round 0 is BC on the demonstration
    source_env = make_env(
        task.env_id,
        seed=SOURCE_SEED + seed,
        num_envs=task.episodes_per_round,
        parallel=cfg.parallel,
        max_episode_steps=steps,
    )
    learner_of = partial(make_learner, source_env, task, cfg, seed)
    returns: list[float] = []
    t0 = time.perf_counter()
    result = dagger(
        EnvSource(source_env, exploration=DET, max_steps=limit),
        expert,
        learner_of,
        buffer,
        DAggerConfig(
            rounds=cfg.relabel_rounds + 1,
            episodes_per_round=task.episodes_per_round,
            beta=Constant(0.0),
            fit=fit,
            seed=seed,
        ),
        on_fit=lambda k, learner: returns.append(score(learner.policy)),
    )
    dagger_s = time.perf_counter() - t0
    source_env.close()
    rows = [r.rows_trained for r in result.rounds]

    # -- BC with as many expert samples as DAgger's last fit used
    matched_env = make_env(
        task.env_id,
        seed=MATCHED_SEED + seed,
        num_envs=task.episodes_per_round,
        max_episode_steps=steps,
    )
    chunks, have = [], 0
    while have < rows[-1]:
        chunk = rollout_episodes(
            matched_env,
            expert.as_actor(),
            task.episodes_per_round,
            exploration=DET,
            max_steps=limit,
        )
        chunks.append(chunk)
        have += chunk.shape[0]
    matched_rows = torch.cat(chunks)[: rows[-1]]
    matched = learner_of()
    fit_bc(matched, matched_rows, fit)
    matched_return = score(matched.policy)
    eval_env.close()

    scores = [normalise(r) for r in returns]
    reached = [k for k in range(1, len(scores)) if scores[k] >= cfg.threshold]
    return {
        "seed": seed,
        "expert_return": expert_return,
        "dagger_returns": returns,
        "dagger_scores": scores,
        "rows": rows,
        "bc_return": returns[0],
        "bc_score": scores[0],
        "bc_matched_return": matched_return,
        "bc_matched_score": normalise(matched_return),
        "bc_matched_rows": int(matched_rows.shape[0]),
        "first_round_reached": reached[0] if reached else None,
        "dagger_seconds": dagger_s,
    }


def fmt(values: list[float], digits: int = 2) -> str:
    m, lo, hi = t_interval(values)
    return f"{m:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def markdown(results: dict, cfg: Config) -> str:
    lines = [
        f"{cfg.seeds} seeds per env; {cfg.eval_episodes} greedy evaluation episodes per learner "
        f"(same initial states for every policy of a seed); score = (R - R_random) / "
        f"(R_expert - R_random); mean [95% t-interval over seeds]. Total time "
        f"{results['seconds']:.0f} s on {results['machine']['cpu_count']} CPU cores "
        f"(`torch.set_num_threads(1)`){' with parallel rollouts' if cfg.parallel else ''}.",
        "",
        "Built-in experts over " + f"{cfg.reference_episodes} episodes (seeded lanes):",
        "",
    ]
    ref_rows = [
        [
            env_id,
            f"{r['expert']['mean']:.1f} [{r['expert']['ci'][0]:.1f}, {r['expert']['ci'][1]:.1f}]",
            f"{r['random']['mean']:.1f}",
        ]
        for env_id, r in results["references"].items()
    ]
    lines += [_report.table(["env", "expert return", "uniform random"], ref_rows), ""]
    rows = []
    for env_id, per in results["tasks"].items():
        seeds = per["seeds"]
        n_reached = sum(s["first_round_reached"] is not None for s in seeds)
        firsts = [s["first_round_reached"] for s in seeds if s["first_round_reached"] is not None]
        last = [s["dagger_scores"][-1] for s in seeds]
        rows.append(
            [
                env_id,
                per["demo"],
                fmt([s["bc_score"] for s in seeds]),
                *[
                    fmt([s["dagger_scores"][k] for s in seeds])
                    for k in range(1, cfg.relabel_rounds + 1)
                ],
                f"{n_reached}/{len(seeds)}"
                + (f" (round {min(firsts)}-{max(firsts)})" if firsts else ""),
                f"{sum(x >= cfg.threshold for x in last)}/{len(seeds)}",
                fmt([s["bc_matched_score"] for s in seeds])
                + f" (N={round(sum(s['bc_matched_rows'] for s in seeds) / len(seeds))})",
                f"{per['seconds']:.0f}",
            ]
        )
    header = [
        "env",
        "demo",
        "BC (same demo)",
        *[f"DAgger r{k}" for k in range(1, cfg.relabel_rounds + 1)],
        f">= {cfg.threshold} within {cfg.relabel_rounds} rounds",
        f">= {cfg.threshold} at r{cfg.relabel_rounds}",
        "BC, matched samples (mean N)",
        "s",
    ]
    lines += ["Normalised scores:", "", _report.table(header, rows), ""]
    ret_rows = []
    for env_id, per in results["tasks"].items():
        seeds = per["seeds"]
        ret_rows.append(
            [
                env_id,
                fmt([s["expert_return"] for s in seeds], 1),
                fmt([s["bc_return"] for s in seeds], 1),
                fmt([s["dagger_returns"][-1] for s in seeds], 1),
                fmt([s["bc_matched_return"] for s in seeds], 1),
                fmt([s["rows"][-1] for s in seeds], 0),
            ]
        )
    lines += [
        "Raw returns (same evaluation states):",
        "",
        _report.table(
            [
                "env",
                "expert",
                "BC",
                f"DAgger r{cfg.relabel_rounds}",
                "BC, matched",
                "expert labels used",
            ],
            ret_rows,
        ),
        "",
        f"![BC vs DAgger](results/{NAME}.png)",
    ]
    return "\n".join(lines)


def figure(results: dict, cfg: Config, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(results["tasks"].items())
    fig, axes = plt.subplots(1, len(tasks), figsize=(4 * len(tasks), 3.4), squeeze=False)
    rounds = list(range(cfg.relabel_rounds + 1))
    for ax, (env_id, per) in zip(axes[0], tasks):
        seeds = per["seeds"]
        for s in seeds:
            ax.plot(rounds, s["dagger_scores"], color="tab:blue", alpha=0.25, lw=0.8)
        stats = [t_interval([s["dagger_scores"][k] for s in seeds]) for k in rounds]
        ax.plot(rounds, [m for m, _, _ in stats], color="tab:blue", marker="o", label="DAgger")
        ax.fill_between(rounds, [lo for _, lo, _ in stats], [hi for _, _, hi in stats], alpha=0.2)
        m, lo, hi = t_interval([s["bc_matched_score"] for s in seeds])
        ax.errorbar(
            [rounds[-1] + 0.15],
            [m],
            yerr=[[m - lo], [hi - m]],
            color="tab:orange",
            marker="s",
            label="BC, matched samples",
        )
        ax.axhline(1.0, color="k", lw=0.8, label="expert")
        ax.axhline(cfg.threshold, color="k", lw=0.8, ls="--")
        ax.set_title(env_id, fontsize=10)
        ax.set_xlabel("DAgger round (0 = BC on the demo)")
        ax.set_xticks(rounds)
        ax.set_ylim(min(-0.1, ax.get_ylim()[0]), 1.1)
    axes[0][0].set_ylabel("normalised return")
    axes[0][0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(cfg: Config, tasks: tuple[Task, ...] = TASKS, log=print) -> dict:
    t_start = time.perf_counter()
    references = {}
    for env_id, expert in REFERENCE_EXPERTS:
        references[env_id] = reference_returns(env_id, expert(), cfg)
        log(f"reference {env_id}: {references[env_id]}")
    out = {}
    for task in tasks:
        t0 = time.perf_counter()
        random_return = references[task.env_id]["random"]["mean"]
        seeds = []
        for seed in range(cfg.seeds):
            record = run_seed(task, seed, cfg, random_return)
            seeds.append(record)
            log(
                f"{task.env_id} seed {seed}: bc {record['bc_score']:.2f} dagger "
                f"{[round(x, 2) for x in record['dagger_scores']]} matched "
                f"{record['bc_matched_score']:.2f} rows {record['rows']}"
            )
        out[task.env_id] = {
            "task": {k: v for k, v in dataclasses.asdict(task).items() if k != "expert"},
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


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run on a tiny budget")
    parser.add_argument("--out", type=Path, default=None, help="write here, not to the README")
    parser.add_argument("--seeds", type=int, default=None)
    parser.add_argument("--parallel", action="store_true", help="ParallelEnv rollouts")
    parser.add_argument("--envs", nargs="*", default=None, help="subset of the env ids")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cfg = QUICK if args.quick else Config()
    if args.seeds is not None:
        cfg = dataclasses.replace(cfg, seeds=args.seeds)
    if args.parallel:
        cfg = dataclasses.replace(cfg, parallel=True)
    tasks = TASKS if not args.envs else tuple(t for t in TASKS if t.env_id in args.envs)
    if not tasks:
        raise ValueError(f"--envs must name some of {[t.env_id for t in TASKS]}")
    results = run(cfg, tasks, log=lambda s: print(s, file=sys.stderr, flush=True))
    results["machine"] = _report.machine()
    target = _report.RESULTS if args.out is None else Path(args.out)
    target.mkdir(parents=True, exist_ok=True)
    figure(results, cfg, target / f"{NAME}.png")
    _report.write(NAME, results, markdown(results, cfg), out_dir=args.out)
    print(markdown(results, cfg))
    return results


if __name__ == "__main__":
    main()

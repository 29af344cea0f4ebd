"""Imitation losses compared: every registered loss x task x seed, BC and DAgger, equal budget.

Which loss, on which kind of task, with what uncertainty. For every task, every loss
of :mod:`imitrl.objectives.registry` that applies to its action space is trained on
the same expert demonstrations with the same budget (gradient steps x batch size,
network size, optimizer), once per seed:

* BC: a learner fitted to the demonstrations (DAgger's round 0);
* DAgger: ``rounds - 1`` relabel rounds later (beta = 0, a fresh learner per round,
  same fit), the learner fitted on everything collected.

Tasks: slippery FrozenLake (score: the exact success probability of the learned
policy in 100 steps, from the MDP, not sampled), CartPole-v1, Pendulum-v1,
InvertedPendulum-v5 (score: mean return over evaluation episodes on held-out seeds)
and the two-way obstacle task of :mod:`imitrl.envs.multimodal` (score: success rate;
plus the fraction of the learner's actions near each of the expert's two modes at
the decision states, and which side its successful episodes passed).

The expert-normalised score is ``(score - random) / (expert - random)``, with the
expert's and a uniformly random policy's scores measured by the same protocol on the
same seeds (averaged over seeds). Intervals are 95% Student-t intervals over seeds.

Every random draw flows from the cell's seed (the learner's initialisation, its
minibatches, its sampling, the envs), so a cell gives the same digits whenever and
wherever (``--jobs``) it runs.

    python benchmarks/loss_functions.py                      # full run, refreshes the README
    python benchmarks/loss_functions.py --jobs 2             # same results, two processes
    python benchmarks/loss_functions.py --quick --out /tmp/x # smoke test (seconds)
    python benchmarks/loss_functions.py --tasks two_way --losses mse diffusion --seeds 3 --out /tmp/x
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import re
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _report
from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.data import DemonstrationBuffer, episode_returns, rollout_episodes
from imitrl.envs import TabularEnv, make_env
from imitrl.envs import multimodal as mm
from imitrl.evaluation import exact_values, t_interval
from imitrl.objectives import registry
from imitrl.objectives.registry import Learner, LearnerConfig, TaskSpec
from imitrl.policies import BetaMixer, Expert, behaviour_policy
from imitrl.policies.experts import as_actor
from imitrl.tabular import TabularMDP, greedy, success_probability, value_iteration

NAME = "loss_functions"
DET, RND = ExplorationType.DETERMINISTIC, ExplorationType.RANDOM


# --------------------------------------------------------------------- protocol
@dataclass(frozen=True)
class Protocol:
    """One task's data and training budget (the same for every loss)."""

    demo_episodes: int
    """expert episodes in the BC dataset (DAgger's round 0)"""
    rounds: int
    """DAgger fits; round 0 is BC, the last is reported as DAgger"""
    episodes_per_round: int
    """learner episodes relabelled by the expert per DAgger round"""
    fit: BCConfig
    """every fit: gradient steps, batch size (the loss comes from the registry)"""
    learner: LearnerConfig
    """network size and learning rate shared by every loss (seeded per cell)"""
    eval_episodes: int
    """evaluation episodes per learner (gym and two-way tasks)"""
    max_episode_steps: int | None = None
    """cap on episode length (None: the env's own limit); used by --quick"""


def quick(protocol: Protocol) -> Protocol:
    """A smoke-test budget: tiny fits, two rounds, two short evaluation episodes."""
    return replace(
        protocol,
        demo_episodes=min(protocol.demo_episodes, 2),
        rounds=2,
        episodes_per_round=1,
        fit=replace(protocol.fit, num_steps=5),
        eval_episodes=2,
        max_episode_steps=30,
    )


class _Uniform(TensorDictModuleBase):
    """A uniformly random policy writing ``ACTION`` (seeded generator)."""

    def __init__(self, action: int | Bounded, seed: int) -> None:
        super().__init__()
        self.action = action
        self.in_keys, self.out_keys = [keys.OBSERVATION], [keys.ACTION]
        self.generator = torch.Generator().manual_seed(seed)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        if isinstance(self.action, int):
            a = torch.randint(self.action, td.batch_size, generator=self.generator)
        else:
            low, high = self.action.space.low, self.action.space.high
            u = torch.rand((*td.batch_size, *low.shape), generator=self.generator)
            a = low + (high - low) * u
        td.set(keys.ACTION, a)
        return td


class Task:
    """A task of the benchmark: its spaces, expert, envs and score."""

    name: str
    score_name: str
    protocol: Protocol

    def spec(self) -> TaskSpec:
        raise NotImplementedError

    def expert(self) -> TensorDictModuleBase:
        """Writes ``EXPERT_ACTION`` (the queryable expert)."""
        raise NotImplementedError

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        raise NotImplementedError

    def max_steps(self) -> int:
        """Safety bound on steps per lane in one rollout."""
        raise NotImplementedError

    def score(self, policy: TensorDictModuleBase, exploration: ExplorationType, seed: int) -> dict:
        """``{"score": float, ...}`` of a policy writing ``ACTION``."""
        raise NotImplementedError

    def random_score(self, seed: int) -> dict:
        spec = self.spec()
        return self.score(_Uniform(spec.action, seed), RND, seed)

    def extras(self, learner: Learner, seed: int) -> dict:
        return {}


class FrozenLake(Task):
    name, score_name = "frozenlake", "exact success"

    def __init__(self, protocol: Protocol) -> None:
        self.protocol = protocol
        self.mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95)
        self.Q = self.mdp.backup(value_iteration(self.mdp, 1000)[-1])  # [S, A] float64
        self.table = greedy(self.Q)

    def advantage(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``Q*(s, a) - mean_b Q*(s, b)``: how much better ``a`` is than a random choice."""
        return (self.Q[obs, action] - self.Q[obs].mean(-1)).float()

    def spec(self) -> TaskSpec:
        return TaskSpec(action=4, num_states=16, advantage=self.advantage)

    def expert(self) -> TensorDictModuleBase:
        return Expert.from_table(self.table)

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        return TabularEnv(self.mdp, batch_size=(lanes,), seed=seed)

    def max_steps(self) -> int:
        return 100_000

    def score(self, policy, exploration, seed) -> dict:
        exact = exact_values(self.mdp, policy, exploration, 100)
        return {"score": exact["success"], "exact_return": exact["return"]}

    def random_score(self, seed: int) -> dict:
        uniform = torch.full((16, 4), 0.25, dtype=torch.float64)
        return {"score": success_probability(self.mdp, uniform, 100)}

    def expert_score(self) -> dict:
        return {"score": success_probability(self.mdp, self.table, 100)}


class Gym(Task):
    """A gymnasium task with a built-in expert; score = mean return over held-out episodes."""

    score_name = "return"

    def __init__(
        self, name: str, env_id: str, expert: Callable[[], Expert], protocol: Protocol
    ) -> None:
        self.name, self.env_id, self._expert, self.protocol = name, env_id, expert, protocol
        probe = make_env(env_id, seed=0)
        self._obs_dim = int(probe.observation_spec[keys.OBSERVATION].shape[-1])
        spec = probe.action_spec_unbatched if hasattr(probe, "action_spec_unbatched") else None
        spec = spec if spec is not None else probe.action_spec
        self._action = int(spec.n) if not isinstance(spec, Bounded) else spec
        probe.close()

    def spec(self) -> TaskSpec:
        return TaskSpec(action=self._action, observation_dim=self._obs_dim)

    def expert(self) -> TensorDictModuleBase:
        return self._expert()

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        return make_env(
            self.env_id,
            seed=seed,
            num_envs=lanes,
            max_episode_steps=self.protocol.max_episode_steps,
        )

    def max_steps(self) -> int:
        return 20_000

    def score(self, policy, exploration, seed) -> dict:
        n = self.protocol.eval_episodes
        env = self.env(seed=10_000 + 100 * seed, lanes=n)  # held-out starts
        summary = episode_returns(
            env, policy, n, exploration=exploration, max_steps=self.max_steps()
        )
        env.close()
        return {"score": float(summary.returns.mean()), "returns": summary.returns.tolist()}


class TwoWay(Task):
    """:mod:`imitrl.envs.multimodal`: score = success rate; mode fractions at the decision states."""

    name, score_name = "two_way", "success"
    decision_states = 1000

    def __init__(self, protocol: Protocol) -> None:
        self.protocol = protocol
        self.geometry = mm.ObstacleGeometry()

    def spec(self) -> TaskSpec:
        return TaskSpec(action=Bounded(-1.0, 1.0, shape=(1,)), observation_dim=2)

    def expert(self) -> TensorDictModuleBase:
        return mm.two_way_expert(self.geometry)

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        return mm.TwoWayObstacleEnv(batch_size=(lanes,), geometry=self.geometry, seed=seed)

    def max_steps(self) -> int:
        return 100 * self.geometry.steps

    def score(self, policy, exploration, seed) -> dict:
        # the expert rides along (beta = 0) only so that the rows carry its labels
        n = self.protocol.eval_episodes
        env = self.env(seed=10_000 + 100 * seed, lanes=min(n, 100))
        behaviour = _behaviour(self.expert(), policy)
        rows = rollout_episodes(
            env, behaviour, n, exploration=exploration, max_steps=self.max_steps()
        )
        success = rows.get((keys.NEXT, keys.REWARD)).reshape(-1) > 0
        side = mm.passing_side(rows, self.geometry)
        wins = int(success.sum())
        above = int(((side > 0) & _episode_success(rows)).sum())
        return {
            "score": wins / n,
            "passed_above": above / wins if wins else None,
        }

    def random_score(self, seed: int) -> dict:
        return self.score(_Uniform(self.spec().action, seed), RND, seed)

    def extras(self, learner: Learner, seed: int) -> dict:
        obs = mm.decision_states(self.decision_states, geometry=self.geometry, seed=seed)
        out = {}
        for exploration, tag in (
            (learner.exploration, "modes"),
            (DET, "modes_det"),
            (RND, "modes_rnd"),
        ):
            with torch.no_grad(), set_exploration_type(exploration):
                td = learner.policy(TensorDict({keys.OBSERVATION: obs}, batch_size=[obs.shape[0]]))
            fractions = mm.mode_fractions(obs, td.get(keys.ACTION), geometry=self.geometry)
            out.update({f"{tag}_{k}": v for k, v in fractions.items()})
        return out


def _behaviour(expert: TensorDictModuleBase, policy: TensorDictModuleBase):
    return behaviour_policy(expert, policy, BetaMixer(0.0))


def _episode_success(rows: TensorDictBase) -> torch.Tensor:
    episode = rows.get(keys.EPISODE)
    reward = rows.get((keys.NEXT, keys.REWARD)).reshape(-1)
    ids = torch.unique(episode)
    return torch.stack([(reward[episode == e] > 0).any() for e in ids])


def _tasks(quick_mode: bool) -> dict[str, Callable[[], Task]]:
    from imitrl.experts import cartpole_expert, inverted_pendulum_expert, pendulum_expert

    def p(protocol: Protocol) -> Protocol:
        return quick(protocol) if quick_mode else protocol

    mlp = LearnerConfig(hidden=(64, 64), lr=1e-3)
    wide = LearnerConfig(hidden=(128, 128), lr=3e-3)
    return {
        "frozenlake": lambda: FrozenLake(
            p(
                Protocol(
                    demo_episodes=1,
                    rounds=4,
                    episodes_per_round=3,
                    fit=BCConfig(num_steps=200),
                    learner=LearnerConfig(lr=0.1),
                    eval_episodes=0,
                )
            )
        ),
        "cartpole": lambda: Gym(
            "cartpole",
            "CartPole-v1",
            cartpole_expert,
            p(Protocol(1, 4, 2, BCConfig(num_steps=1000, batch_size=256), mlp, 10)),
        ),
        "pendulum": lambda: Gym(
            "pendulum",
            "Pendulum-v1",
            pendulum_expert,
            p(Protocol(5, 4, 2, BCConfig(num_steps=2000, batch_size=256), wide, 10)),
        ),
        "inverted_pendulum": lambda: Gym(
            "inverted_pendulum",
            "InvertedPendulum-v5",
            inverted_pendulum_expert,
            p(Protocol(2, 4, 1, BCConfig(num_steps=2000, batch_size=256), wide, 10)),
        ),
        "two_way": lambda: TwoWay(
            p(Protocol(50, 4, 20, BCConfig(num_steps=3000, batch_size=256), wide, 100))
        ),
    }


TASKS = ("frozenlake", "cartpole", "pendulum", "inverted_pendulum", "two_way")


# ------------------------------------------------------------------------ cells
def reference_cell(task_name: str, seed: int, quick_mode: bool) -> list[dict]:
    """The expert's and a uniformly random policy's scores on the task's protocol."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    task = _tasks(quick_mode)[task_name]()
    if isinstance(task, FrozenLake):
        expert = task.expert_score()
    else:
        expert = task.score(as_actor(task.expert()), DET, seed)
    rows = []
    for who, result in (("expert", expert), ("random", task.random_score(seed))):
        rows.append({"task": task_name, "policy": who, "seed": seed, **result})
    return rows


def loss_cell(task_name: str, loss: str, seed: int, quick_mode: bool) -> list[dict]:
    """Train ``loss`` on ``task_name`` with ``seed``: one row for BC, one for DAgger."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)  # global draws (TorchRL's samplers) start from the seed too
    t0 = time.perf_counter()
    task = _tasks(quick_mode)[task_name]()
    proto = task.protocol
    spec = task.spec()
    config = replace(proto.learner, seed=seed)
    exploration = registry.build(loss, spec, config).exploration

    # 1. demonstrations: the expert drives the env, every row is labelled
    env = task.env(seed=seed, lanes=proto.episodes_per_round)
    expert = task.expert()
    buffer = DemonstrationBuffer(num_states=spec.num_states)
    buffer.extend(
        rollout_episodes(
            env,
            as_actor(expert),
            proto.demo_episodes,
            exploration=DET,
            max_steps=task.max_steps(),
        )
    )
    demo_rows = len(buffer)

    # 2. DAgger, whose round 0 is BC; evaluate the first and the last fit
    results: dict[int, dict] = {}
    fit_seconds: list[float] = []

    def fit(learner: Learner, buf: DemonstrationBuffer):
        t = time.perf_counter()
        out = fit_bc(learner, buf, replace(proto.fit, seed=seed), loss_module=learner.loss)
        fit_seconds.append(time.perf_counter() - t)
        return out

    def on_fit(k: int, learner: Learner) -> None:
        if k in (0, proto.rounds - 1):
            t = time.perf_counter()
            result = task.score(learner.policy, learner.exploration, seed)
            result.update(task.extras(learner, seed))
            result["eval_seconds"] = time.perf_counter() - t
            results[k] = result

    out = dagger(
        EnvSource(env, exploration=exploration, max_steps=task.max_steps()),
        expert,
        lambda: registry.build(loss, spec, config),
        buffer,
        DAggerConfig(rounds=proto.rounds, episodes_per_round=proto.episodes_per_round, seed=seed),
        on_fit=on_fit,
        fit=fit,
    )
    env.close()
    rows = []
    for algorithm, k in (("bc", 0), ("dagger", proto.rounds - 1)):
        record = out.rounds[k]
        rows.append(
            {
                "task": task_name,
                "loss": loss,
                "seed": seed,
                "algorithm": algorithm,
                "exploration": str(exploration).split(".")[-1].lower(),
                "rows_trained": record.rows_trained,
                "demo_rows": demo_rows,
                "final_loss": record.fit.final_loss,
                "fit_seconds": fit_seconds[k],
                **results[k],
            }
        )
    rows[-1]["cell_seconds"] = rows[0]["cell_seconds"] = time.perf_counter() - t0
    return rows


# ------------------------------------------------------------------- statistics
def summarize(rows: list[dict], references: list[dict]) -> dict[str, Any]:
    """Per (task, loss, algorithm): mean and interval of the score and the normalised score."""
    ref = {}
    for task in {r["task"] for r in references}:
        e = t_interval(
            [r["score"] for r in references if r["task"] == task and r["policy"] == "expert"]
        )
        z = t_interval(
            [r["score"] for r in references if r["task"] == task and r["policy"] == "random"]
        )
        ref[task] = {"expert": e[0], "random": z[0]}
    for r in rows:
        e, z = ref[r["task"]]["expert"], ref[r["task"]]["random"]
        r["normalized"] = (r["score"] - z) / (e - z) if e != z else math.nan
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["task"], r["loss"], r["algorithm"]), []).append(r)
    summary = []
    for (task, loss, algorithm), rs in groups.items():
        entry = {"task": task, "loss": loss, "algorithm": algorithm, "seeds": len(rs)}
        for metric in ("score", "normalized"):
            entry[metric] = t_interval([r[metric] for r in rs])
        if task == "two_way":
            for metric in [k for k in rs[0] if k.startswith("modes") or k == "passed_above"]:
                entry[metric] = t_interval([r[metric] for r in rs])
        summary.append(entry)
    return {"reference": ref, "groups": summary}


# ------------------------------------------------------------------------ report
def _fmt(ci: tuple[float, float, float], digits: int = 2, *, unit: bool = False) -> str:
    """``mean [lo, hi]``; ``unit``: a probability, its interval clipped to [0, 1]."""
    mean, lo, hi = ci
    if math.isnan(mean):
        return "-"
    if math.isnan(lo):
        return f"{mean:.{digits}f}"
    if unit:
        lo, hi = max(lo, 0.0), min(hi, 1.0)
    return f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


UNIT_SCORES = ("frozenlake", "two_way")
"""tasks whose score is a probability"""


def _digits(task: str) -> int:
    return 3 if task in ("frozenlake", "two_way") else 1


def _losses(groups: list[dict], task: str | None = None) -> list[str]:
    """Loss names in the groups (of ``task``), registry order first."""
    present = [g["loss"] for g in groups if task is None or g["task"] == task]
    known = [n for n in registry.names() if n in present]
    return known + [n for n in dict.fromkeys(present) if n not in known]


def verdict(group: dict) -> str:
    """A sentence from the measured mode fractions (never assumed)."""
    below, middle, above = (group[f"modes_{k}"] for k in ("below", "middle", "above"))
    if below[1] > 0.1 and above[1] > 0.1:
        return "keeps both modes (each mode's lower 95% bound > 0.1)"
    if middle[0] > 0.5:
        return "averages the modes (most actions near their mean, 0)"
    if min(below[0], above[0]) < 0.05 and max(below[0], above[0]) > 0.5:
        return "collapses to one mode"
    return "mixed: neither both modes nor one clearly"


def markdown(
    summary: dict, config: dict, protocols: dict[str, dict], wall: float, figure: str | None
) -> str:
    groups = summary["groups"]
    jobs = config["jobs"]
    # where the files went does not change a number
    command = re.sub(
        r" --out \S+", "", config.get("command", "python benchmarks/loss_functions.py")
    )
    lines = [
        f"{'Smoke' if config['quick'] else 'Full'} run: `{command}`, {config['seeds']} seeds, "
        f"**wall time {wall / 60:.1f} min** on {config.get('cpu_count', '?')} CPU cores "
        f"({jobs} process{'es' if jobs > 1 else ''}, 1 torch thread each; wall times move with "
        "the machine's load, the scores do not).",
        "",
        "Score: FrozenLake = exact success probability (from the MDP); CartPole, Pendulum, "
        "InvertedPendulum = mean return over held-out episodes; two-way = success rate. "
        "Normalised = (score - random) / (expert - random). Mean [95% t-interval] over seeds "
        "(clipped to [0, 1] for probabilities). "
        "BC = DAgger's round 0; DAgger = its last round.",
        "",
    ]
    ref = summary["reference"]
    header = ["task", "loss", "BC score", "BC normalised", "DAgger score", "DAgger normalised"]
    table_rows = []
    for task in TASKS:
        if task not in ref:
            continue
        d = _digits(task)
        table_rows.append(
            [
                f"**{task}**",
                f"expert {ref[task]['expert']:.{d}f}, random {ref[task]['random']:.{d}f}",
                "",
                "",
                "",
                "",
            ]
        )
        for loss in _losses(groups, task):
            bc = [g for g in groups if (g["task"], g["loss"], g["algorithm"]) == (task, loss, "bc")]
            dg = [
                g
                for g in groups
                if (g["task"], g["loss"], g["algorithm"]) == (task, loss, "dagger")
            ]
            if not bc:
                continue
            table_rows.append(
                [
                    task,
                    loss,
                    _fmt(bc[0]["score"], d, unit=task in UNIT_SCORES),
                    _fmt(bc[0]["normalized"]),
                    _fmt(dg[0]["score"], d, unit=task in UNIT_SCORES),
                    _fmt(dg[0]["normalized"]),
                ]
            )
    lines.append(_report.table(header, table_rows))
    two_way = [g for g in groups if g["task"] == "two_way"]
    if two_way:
        lines += [
            "",
            "**Two-way obstacle: does the learner keep both of the expert's modes?** Fraction of "
            f"the learner's actions at {TwoWay.decision_states} decision states within 0.25 of the "
            "expert's pass-below action (-0.5), of its pass-above action (+0.5), and near neither "
            "(of which *middle*: within 0.25 of the modes' mean, 0); the "
            "policy acts as its entry says (sampled for diffusion, greedy/mean otherwise). "
            "Mean [95% t-interval] over seeds; the verdict is computed from these numbers.",
            "",
        ]
        header = [
            "loss",
            "algorithm",
            "below",
            "neither",
            "(middle)",
            "above",
            "success",
            "passed above",
            "verdict",
        ]
        table_rows = []
        for loss in _losses(two_way):
            for algorithm in ("bc", "dagger"):
                g = [x for x in two_way if (x["loss"], x["algorithm"]) == (loss, algorithm)]
                if not g:
                    continue
                g = g[0]
                table_rows.append(
                    [
                        loss,
                        algorithm,
                        _fmt(g["modes_below"], unit=True),
                        _fmt(g["modes_neither"], unit=True),
                        _fmt(g["modes_middle"], unit=True),
                        _fmt(g["modes_above"], unit=True),
                        _fmt(g["score"], unit=True),
                        _fmt(g["passed_above"], unit=True),
                        verdict(g),
                    ]
                )
        lines.append(_report.table(header, table_rows))
    lines += ["", "Budget per task (identical for every loss; one learner per seed and round):", ""]
    header = [
        "task",
        "demo episodes",
        "DAgger rounds x episodes",
        "fit steps x batch",
        "network",
        "lr",
        "eval",
    ]
    table_rows = []
    for task, p in protocols.items():
        table_rows.append(
            [
                task,
                p["demo_episodes"],
                f"{p['rounds'] - 1} x {p['episodes_per_round']}",
                f"{p['fit']['num_steps']} x {p['fit']['batch_size'] or 'full'}",
                "table" if task == "frozenlake" else "x".join(map(str, p["learner"]["hidden"])),
                p["learner"]["lr"],
                "exact" if task == "frozenlake" else f"{p['eval_episodes']} episodes",
            ]
        )
    lines.append(_report.table(header, table_rows))
    if figure:
        lines += ["", f"![normalised scores and two-way mode fractions]({figure})"]
    return "\n".join(lines)


def figure(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = summary["groups"]
    tasks = [t for t in TASKS if any(g["task"] == t for g in groups)]
    cols = 3
    rows = math.ceil((len(tasks) + 1) / cols)
    fig, grid = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.6 * rows), squeeze=False)
    axes = list(grid.reshape(-1))
    for ax in axes[len(tasks) + 1 :]:
        ax.set_visible(False)
    axes = [*axes[: len(tasks)], axes[len(tasks)]]
    for ax, task in zip(axes, tasks):
        losses = _losses(groups, task)
        for j, (algorithm, colour) in enumerate((("bc", "tab:blue"), ("dagger", "tab:orange"))):
            for i, loss in enumerate(losses):
                g = next(
                    x
                    for x in groups
                    if (x["task"], x["loss"], x["algorithm"]) == (task, loss, algorithm)
                )
                mean, lo, hi = g["normalized"]
                err = [[mean - lo], [hi - mean]] if not math.isnan(lo) else None
                ax.barh(
                    i + 0.4 * j - 0.2,
                    mean,
                    height=0.4,
                    color=colour,
                    xerr=err,
                    capsize=2,
                    label=algorithm if i == 0 else None,
                )
        ax.set_yticks(range(len(losses)), losses)
        ax.axvline(1.0, color="k", lw=0.8, ls="--")
        ax.axvline(0.0, color="k", lw=0.8)
        ax.set_title(task)
        ax.set_xlabel("expert-normalised score")
        ax.invert_yaxis()
    axes[0].legend(loc="lower right")
    ax = axes[-1]
    two_way = [g for g in groups if g["task"] == "two_way" and g["algorithm"] == "bc"]
    if two_way:
        names = [g["loss"] for g in two_way]
        left = [0.0] * len(names)
        parts = {
            "near -0.5 (below)": [g["modes_below"][0] for g in two_way],
            "near 0 (the mean)": [g["modes_middle"][0] for g in two_way],
            "elsewhere": [g["modes_neither"][0] - g["modes_middle"][0] for g in two_way],
            "near +0.5 (above)": [g["modes_above"][0] for g in two_way],
        }
        colours = ("tab:green", "tab:red", "tab:gray", "tab:purple")
        for (part, values), colour in zip(parts.items(), colours):
            ax.barh(names, values, left=left, color=colour, label=part)
            left = [a + b for a, b in zip(left, values)]
        ax.set_xlim(0, 1)
        ax.set_title("two_way, BC: actions at the decision")
        ax.set_xlabel("fraction of actions (mean over seeds)")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, fontsize=8)
        ax.invert_yaxis()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -------------------------------------------------------------------------- main
def run(
    *,
    tasks: list[str],
    losses: list[str] | None,
    seeds: int,
    quick_mode: bool,
    jobs: int = 1,
) -> dict[str, Any]:
    """Every (loss, task, seed) cell and the expert/random references; returns the raw rows."""
    factories = _tasks(quick_mode)
    cells, refs = [], []
    for task_name in tasks:
        spec = factories[task_name]().spec()
        for seed in range(seeds):
            refs.append((task_name, seed, quick_mode))
            for loss in registry.names(spec):
                if losses is None or loss in losses:
                    cells.append((task_name, loss, seed, quick_mode))
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            ref_rows = [r for rows in pool.map(reference_cell, *zip(*refs)) for r in rows]
            rows = [r for rs in pool.map(loss_cell, *zip(*cells)) for r in rs]
    else:
        ref_rows = [r for args in refs for r in reference_cell(*args)]
        rows = []
        for i, args in enumerate(cells):
            t = time.perf_counter()
            rows += loss_cell(*args)
            print(
                f"[{i + 1}/{len(cells)}] {args[0]} {args[1]} seed {args[2]}: "
                f"bc {rows[-2]['score']:.3f} dagger {rows[-1]['score']:.3f} "
                f"({time.perf_counter() - t:.1f} s)",
                flush=True,
            )
    protocols = {t: asdict(factories[t]().protocol) for t in tasks}
    return {"rows": rows, "references": ref_rows, "protocols": protocols}


def report(raw: dict[str, Any], out: Path | None) -> str:
    """Summary, figure, results JSON and (unless ``out``) the README block, from raw rows."""
    summary = summarize(raw["rows"], raw["references"])
    raw["config"].setdefault("cpu_count", raw.get("machine", {}).get("cpu_count", "?"))
    out_dir = _report.RESULTS if out is None else out
    out_dir.mkdir(parents=True, exist_ok=True)
    fig_path = out_dir / f"{NAME}.png"
    figure(summary, fig_path)
    md = markdown(
        summary, raw["config"], raw["protocols"], raw["wall_seconds"], f"results/{fig_path.name}"
    )
    payload = {**raw, "summary": summary}
    path = _report.write(NAME, json.loads(json.dumps(payload, default=str)), md, out_dir=out)
    print(md)
    print(f"\nwrote {path} and {fig_path}")
    return md


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny budget, one seed (smoke test)")
    parser.add_argument(
        "--seeds", type=int, default=None, help="seeds per cell (default 5; 1 with --quick)"
    )
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--losses", nargs="+", default=None, help="registry names (default: all)")
    parser.add_argument(
        "--import",
        dest="modules",
        nargs="+",
        default=[],
        metavar="MODULE",
        help="import these modules first (their @register entries join the run)",
    )
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (same results)")
    parser.add_argument(
        "--out", type=Path, default=None, help="write results here (README untouched)"
    )
    parser.add_argument(
        "--render",
        type=Path,
        default=None,
        metavar="JSON",
        help="re-render the table and figure from a results file instead of running",
    )
    args = parser.parse_args(argv)
    for module in args.modules:
        importlib.import_module(module)
    if args.render is not None:
        report(json.loads(args.render.read_text()), args.out)
        return
    for loss in args.losses or []:
        registry.get(loss)
    torch.set_num_threads(1)
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else 5)
    t0 = time.perf_counter()
    raw = run(
        tasks=args.tasks, losses=args.losses, seeds=seeds, quick_mode=args.quick, jobs=args.jobs
    )
    raw["wall_seconds"] = time.perf_counter() - t0
    raw["config"] = {
        "seeds": seeds,
        "tasks": args.tasks,
        "losses": args.losses,
        "quick": args.quick,
        "jobs": args.jobs,
        "cpu_count": os.cpu_count(),
        "command": " ".join(["python benchmarks/loss_functions.py", *(argv or sys.argv[1:])]),
    }
    raw["losses"] = {
        e.name: {"actions": e.actions, "summary": e.summary} for e in registry.entries()
    }
    report(raw, args.out)
    print(f"wall time {raw['wall_seconds']:.0f} s")


if __name__ == "__main__":
    main()

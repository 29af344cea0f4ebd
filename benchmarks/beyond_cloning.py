"""Beyond cloning: BC, DAgger, GAIL, AIRL (and exact IRL on FrozenLake) from the same
demonstrations, scored against environment steps and against expert queries.

Per task and seed, every method starts from the same demonstration (the bc_vs_dagger
budgets: one expert episode, CartPole-v1 cut to its first 25 steps; FrozenLake: the one
episode of loss_functions' FrozenLake protocol). The cells:

* ``reference``: the expert's and a uniformly random policy's scores, which normalise
  every learner's: ``(R - R_random) / (R_expert - R_random)``. Gym tasks: mean return
  over ``eval_episodes`` greedy episodes from the seed's evaluation states (the same for
  every policy, as in bc_vs_dagger); FrozenLake: exact success probability in 100 steps.
* ``dagger``: bc_vs_dagger's ``run_seed`` (round 0 = BC on the demonstration, then
  ``relabel_rounds`` rounds with beta = 0, and BC on as many expert rows as DAgger's
  last fit, "BC matched"); FrozenLake: a tabular learner, scored exactly.
* ``gail`` / ``airl``: ``imitrl.algorithms.adversarial`` (PPO generator) for the task's
  env-step budget (``ADVERSARIAL``), the learner evaluated every ``eval_every`` rounds.
  FrozenLake's integer states are fed one-hot (the adversarial learners read vectors)
  and the greedy policy on the 16 states is scored exactly.
* ``irl`` (FrozenLake only): exact maximum-causal-entropy IRL (``imitrl.tabular.maxent_irl``,
  reward on the state entered, as the FrozenLake study's section 8), its greedy plan
  scored exactly. It uses the transition kernel and no environment step.

Axes. Environment steps = steps the *learner* acted in the env (DAgger's relabelled
rollouts, GAIL/AIRL's generator steps; BC and IRL take none; the demonstration's own
steps are counted as expert queries). Expert queries = expert actions used: the
demonstration rows, plus DAgger's labels. Intervals are 95% Student-t over seeds.

Every cell is a pure function of (task, method, seed): ``--jobs N`` runs them in N
processes with the same digits.

    python benchmarks/beyond_cloning.py                    # full run: results/ and README
    python benchmarks/beyond_cloning.py --quick            # smoke run, temporary directory
    python benchmarks/beyond_cloning.py --jobs 2 --tasks CartPole-v1 frozenlake \\
        --out benchmarks/results                          # a subset, README untouched
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Unbounded
from torchrl.envs import EnvBase, Transform, TransformedEnv
from torchrl.envs.utils import set_exploration_type

import _report
import bc_vs_dagger as bvd
from _beyond_cloning_report import figure, markdown
from _common import DET, reference_returns, returns, rollout, source
from _loss_functions.tasks import tasks as loss_function_tasks
from imitrl import keys
from imitrl.algorithms import Constant, DAggerConfig, dagger
from imitrl.algorithms.adversarial import AIRLConfig, GAILConfig, airl, gail
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.learners import ActorCritic, TaskSpec, build
from imitrl.policies import as_actor
from imitrl.tabular import success_probability
from imitrl.tabular.maxent_irl import (
    Demonstrations,
    maxent_irl,
    next_state_features,
    time_indexed_state_distributions,
)

NAME = "beyond_cloning"
LAKE = "frozenlake"
GYM_TASKS = {t.env_id: t for t in bvd.TASKS if t.env_id != "InvertedDoublePendulum-v5"}
TASK_NAMES = (LAKE, *GYM_TASKS)
METHODS = ("dagger", "gail", "airl", "irl")
ADVERSARIAL_SEED = 3_000
"""GAIL/AIRL's env is seeded ADVERSARIAL_SEED + seed (bc_vs_dagger's seeds: demo = seed)"""


@dataclass(frozen=True)
class Adversarial:
    """One task's GAIL/AIRL budget and generator (identical for GAIL and AIRL)."""

    total_steps: int
    """environment steps of the generator: the budget"""
    eval_every: int
    """rounds between evaluations of the learner (and after the last round)"""
    rollout_steps: int = 2048
    """environment steps per round"""
    lr: float = 3e-4
    """Adam learning rate of the policy and value heads (PPO)"""
    gamma: float = 0.99
    """discount of GAE (and of AIRL's shaping and the absorbing state's value)"""
    minibatch_size: int = 256
    """rows per PPO gradient step"""
    absorbing: bool = False
    """DAC's absorbing states (for episodes that end at a goal; see the adversarial
    package's ``absorbing`` module)"""
    normalizer_warmup: int = 0
    """env steps of the untrained learner added to the normaliser's statistics (counted)"""
    anneal_lr: bool = False
    """the generator's learning rate falls linearly over the rounds (``anneal_lr``)"""
    hidden: tuple[int, ...] = (64, 64)
    """hidden sizes of the learner's policy and value MLPs (and the discriminator's)"""
    airl_entropy_weight: float = 1.0
    """AIRL's ``w`` in the generator's reward ``f - w log pi`` (``AIRLConfig``)"""


ADVERSARIAL = {
    LAKE: Adversarial(total_steps=5_120, eval_every=1, rollout_steps=1024, absorbing=True),
    "CartPole-v1": Adversarial(total_steps=20_480, eval_every=2),
    "Pendulum-v1": Adversarial(
        total_steps=61_440,
        eval_every=3,
        lr=1e-3,
        gamma=0.9,
        anneal_lr=True,
        airl_entropy_weight=0.0,
    ),
    "InvertedPendulum-v5": Adversarial(
        total_steps=40_960, eval_every=4, minibatch_size=64, normalizer_warmup=2_048
    ),
}
"""the per-task GAIL/AIRL env-step budgets (rounded up to whole rounds) and generators.

Chosen in trial runs (1-5 seeds) to fit the whole run in about 45 minutes on 2 cores:
FrozenLake's demonstrations end at the goal, so its learned reward gets absorbing states
(DAC; the survival tasks keep GAIL's living bonus, which suits them: the adversarial
package's ``absorbing`` module says why and what it measured). Pendulum's PPO takes
rl-zoo's Pendulum settings (gamma 0.9, lr 1e-3; at gamma 0.99 PPO learns Pendulum far
slower) over 61,440 steps with the rate annealed linearly (at 30,720 steps and a constant
rate AIRL ended at 0.9 on 11 of 15 seeds outside the reported ones: some still rising,
some fallen back from the expert; annealed at 61,440, 13 of 15, the README says which),
and its AIRL generator is paid ``f`` alone (``entropy_weight`` 0: at the paper's
1, ``-log pi`` pays a Gaussian generator for noise, and AIRL ended at 0.62 of the expert,
0 of 5 seeds at 0.9; the survival tasks keep 1, their generator's living bonus, without
which CartPole and InvertedPendulum collapse to 9- and 2-step episodes). InvertedPendulum's takes the MuJoCo PPO minibatch of 64 (CleanRL, SB3), and its
normaliser sees 2,048 steps of the untrained learner beside the demonstration: the
expert holds the pole so still (feature std ~1e-3) that the learner's own states would
otherwise normalise to hundreds and saturate its tanh networks."""


@dataclass(frozen=True)
class Config:
    """The whole run."""

    seeds: int = 5
    """training seeds per task"""
    relabel_rounds: int = 5
    """DAgger rounds after the BC fit (bc_vs_dagger's)"""
    eval_episodes: int = 50
    """greedy evaluation episodes per gym learner (one lane each, the seed's initial states)"""
    threshold: float = 0.9
    """normalised score that counts as reaching the expert (the issue's target)"""
    irl_steps: int = 100
    """Adam steps of the exact IRL fit (the FrozenLake study's)"""
    irl_lr: float = 0.5
    """Adam learning rate of the exact IRL fit (the FrozenLake study's)"""
    max_episode_steps: int | None = None
    """override every gym env's time limit (the smoke run)"""
    adversarial_steps: int | None = None
    """override every task's GAIL/AIRL budget"""
    quick: bool = False
    """smoke budgets for every fit (bc_vs_dagger's QUICK, a few PPO steps)"""


QUICK = Config(
    seeds=1, relabel_rounds=1, eval_episodes=2, irl_steps=5, max_episode_steps=30,
    adversarial_steps=64, quick=True,
)  # fmt: skip


def adversarial_budget(task: str, cfg: Config) -> Adversarial:
    budget = ADVERSARIAL[task]
    if cfg.adversarial_steps is None:
        return budget
    return dataclasses.replace(
        budget,
        total_steps=cfg.adversarial_steps,
        rollout_steps=min(budget.rollout_steps, cfg.adversarial_steps),
        normalizer_warmup=min(budget.normalizer_warmup, cfg.adversarial_steps),
    )


def adversarial_config(method: str, budget: Adversarial, cfg: Config, seed: int):
    """GAIL's or AIRL's config: the budget, the library's defaults, tiny steps when quick."""
    fields = dict(
        total_steps=budget.total_steps,
        rollout_steps=budget.rollout_steps,
        gamma=budget.gamma,
        minibatch_size=budget.minibatch_size,
        absorbing=budget.absorbing,
        normalizer_warmup=budget.normalizer_warmup,
        anneal_lr=budget.anneal_lr,
        discriminator_hidden=budget.hidden,
        seed=seed,
    )
    if cfg.quick:
        fields.update(ppo_epochs=1, minibatch_size=32, discriminator_updates=1,
                      discriminator_batch=16)  # fmt: skip
    if method == "gail":
        return GAILConfig(**fields)
    return AIRLConfig(**fields, entropy_weight=budget.airl_entropy_weight)


def bvd_config(cfg: Config) -> bvd.Config:
    """bc_vs_dagger's config for its demonstrations, evaluations and DAgger cells."""
    base = bvd.QUICK if cfg.quick else bvd.Config()
    return dataclasses.replace(
        base,
        seeds=cfg.seeds,
        relabel_rounds=cfg.relabel_rounds,
        eval_episodes=cfg.eval_episodes,
        max_episode_steps=cfg.max_episode_steps,
    )


# --------------------------------------------------------------------- FrozenLake
class OneHotObservation(Transform):
    """Integer states ``[*B]`` -> float32 one-hot ``[*B, S]`` under ``OBSERVATION``."""

    def __init__(self, num_states: int) -> None:
        super().__init__(in_keys=[keys.OBSERVATION], out_keys=[keys.OBSERVATION])
        self.num_states = num_states

    def _apply_transform(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.one_hot(obs.long(), self.num_states).float()

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec):
        old = observation_spec[keys.OBSERVATION]
        observation_spec[keys.OBSERVATION] = Unbounded(
            shape=(*old.shape, self.num_states), dtype=torch.float32
        )
        return observation_spec


def lake_task(cfg: Config):
    """loss_functions' FrozenLake task: slippery lake, value-iteration expert, exact score."""
    return loss_function_tasks(cfg.quick)[LAKE]()


def lake_demonstration(task, seed: int) -> DemonstrationBuffer:
    """The task's demonstration episodes (loss_functions' protocol), env seeded ``seed``."""
    env = task.env(seed=seed, lanes=1)
    buffer = DemonstrationBuffer(num_states=task.spec().num_states)
    buffer.extend(
        rollout(env, as_actor(task.expert()), task.protocol.demo_episodes,
                exploration=DET, max_steps=task.max_steps())
    )  # fmt: skip
    env.close()
    return buffer


def one_hot_rows(rows: TensorDictBase, num_states: int) -> TensorDict:
    """Demonstration rows with their observations (and next observations) one-hot."""
    out = rows.clone()
    for key in (keys.OBSERVATION, (keys.NEXT, keys.OBSERVATION)):
        if key in out.keys(include_nested=True):
            out.set(key, torch.nn.functional.one_hot(out.get(key).long(), num_states).float())
    return out


def lake_greedy_table(learner: ActorCritic, num_states: int) -> torch.Tensor:
    """``[S]`` the learner's greedy action on every (one-hot) state."""
    td = TensorDict({keys.OBSERVATION: torch.eye(num_states)}, batch_size=[num_states])
    with torch.no_grad(), set_exploration_type(DET):
        return learner.policy(td).get(keys.ACTION).long()


# ------------------------------------------------------------------------- cells
def reference_cell(task_name: str, seed: int, cfg: Config) -> dict:
    """The expert's and the uniform policy's scores on the seed's evaluation protocol."""
    torch.set_num_threads(1)
    if task_name == LAKE:
        task = lake_task(cfg)
        expert, rnd = task.expert_score(seed)["score"], task.random_score(seed)["score"]
    else:
        task, bcfg = GYM_TASKS[task_name], bvd_config(cfg)
        n, eval_seed = cfg.eval_episodes, bvd.EVAL_SEED + seed
        env = make_env(
            task_name, seed=eval_seed, num_envs=n, max_episode_steps=cfg.max_episode_steps
        )
        limit = 4 * bvd.horizon(task_name, bcfg)
        ref = reference_returns(env, task.expert(), n, seed=eval_seed, max_steps=limit)
        expert, rnd = float(ref["expert"].mean()), float(ref["random"].mean())
        env.close()
    return {"task": task_name, "method": "reference", "seed": seed, "expert": expert,
            "random": rnd}  # fmt: skip


def dagger_cell(task_name: str, seed: int, cfg: Config) -> dict:
    """BC (round 0) and DAgger's rounds; points at (learner env steps, expert queries)."""
    torch.set_num_threads(1)
    if task_name == LAKE:
        return lake_dagger_cell(seed, cfg)
    record = bvd.run_seed(GYM_TASKS[task_name], seed, bvd_config(cfg))
    rows = record["rows"]
    points = [
        {"env_steps": n - rows[0], "expert_queries": n, "raw": r}
        for n, r in zip(rows, record["dagger_returns"])
    ]
    extra = {"raw": record["bc_matched_return"], "expert_queries": record["bc_matched_rows"]}
    return {"task": task_name, "method": "dagger", "seed": seed, "points": points,
            "bc_matched": extra, "seconds": record["dagger_seconds"]}  # fmt: skip


def lake_dagger_cell(seed: int, cfg: Config) -> dict:
    task = lake_task(cfg)
    proto, t0 = task.protocol, time.perf_counter()
    buffer = lake_demonstration(task, seed)
    env = task.env(seed=bvd.SOURCE_SEED + seed, lanes=proto.episodes_per_round)
    scores: list[float] = []
    result = dagger(
        source(env, exploration=DET, max_steps=task.max_steps()),
        task.expert(),
        lambda: build("cross_entropy", TaskSpec(action=4, num_states=16), lr=proto.learner.lr),
        buffer,
        DAggerConfig(
            rounds=cfg.relabel_rounds + 1,
            episodes_per_round=proto.episodes_per_round,
            beta=Constant(0.0),
            bc=dataclasses.replace(proto.bc, seed=seed),
            seed=seed,
        ),
        on_fit=lambda k, learner: scores.append(task.score(learner.policy, DET, seed)["score"]),
    )
    env.close()
    rows = [r.rows_trained for r in result.rounds]
    points = [
        {"env_steps": n - rows[0], "expert_queries": n, "raw": s} for n, s in zip(rows, scores)
    ]
    return {"task": LAKE, "method": "dagger", "seed": seed, "points": points,
            "seconds": time.perf_counter() - t0}  # fmt: skip


@dataclass
class AdversarialSetup:
    """What a GAIL/AIRL cell trains and how it scores: the env, the seed's demonstration,
    a fresh learner, ``score(learner) -> raw score`` and what to close at the end."""

    env: EnvBase
    buffer: DemonstrationBuffer
    learner: ActorCritic
    score: Callable[[ActorCritic], float]
    envs: list[EnvBase]


def lake_adversarial(seed: int, cfg: Config, budget: Adversarial) -> AdversarialSetup:
    """FrozenLake one-hot (GAIL/AIRL learners read vectors); greedy policy scored exactly."""
    task = lake_task(cfg)
    S = task.spec().num_states
    env = TransformedEnv(task.env(seed=ADVERSARIAL_SEED + seed, lanes=1), OneHotObservation(S))
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(one_hot_rows(lake_demonstration(task, seed).data, S))
    learner = build(
        "for_env",
        TaskSpec.from_specs(S, 4),
        head="categorical",
        hidden=budget.hidden,
        lr=budget.lr,
        seed=seed,
        normalize=False,
        value=True,  # PPO's critic
    )

    def score(learner: ActorCritic) -> float:
        return success_probability(task.mdp, lake_greedy_table(learner, S), 100)

    return AdversarialSetup(env, buffer, learner, score, [env])


def gym_adversarial(
    task_name: str, seed: int, cfg: Config, budget: Adversarial
) -> AdversarialSetup:
    """bc_vs_dagger's demonstration; a categorical (discrete) or tanh-normal (continuous)
    learner, since PPO needs log pi; mean greedy return on the seed's evaluation states."""
    task, bcfg = GYM_TASKS[task_name], bvd_config(cfg)
    buffer = bvd.demonstration(task, seed, bcfg)
    env = make_env(task_name, seed=ADVERSARIAL_SEED + seed, max_episode_steps=cfg.max_episode_steps)
    head = "categorical" if task.head == "categorical" else "tanh_normal"
    learner = build(
        "for_env", env, head=head, hidden=budget.hidden, lr=budget.lr, seed=seed, value=True
    )
    n, eval_seed = cfg.eval_episodes, bvd.EVAL_SEED + seed
    eval_env = make_env(
        task_name, seed=eval_seed, num_envs=n, max_episode_steps=cfg.max_episode_steps
    )
    limit = 4 * bvd.horizon(task_name, bcfg)

    def score(learner: ActorCritic) -> float:
        eval_env.set_seed(eval_seed)
        return float(returns(eval_env, learner.policy, n, exploration=DET, max_steps=limit).mean())

    return AdversarialSetup(env, buffer, learner, score, [env, eval_env])


def adversarial_cell(task_name: str, method: str, seed: int, cfg: Config) -> dict:
    """GAIL or AIRL from the seed's demonstration, evaluated every ``eval_every`` rounds."""
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    budget = adversarial_budget(task_name, cfg)
    setup = (
        lake_adversarial(seed, cfg, budget)
        if task_name == LAKE
        else gym_adversarial(task_name, seed, cfg, budget)
    )
    rounds = -(-budget.total_steps // budget.rollout_steps)
    points: list[dict] = []

    def on_round(k: int, learner: ActorCritic, steps: int) -> dict | None:
        if (k + 1) % budget.eval_every and k + 1 != rounds:
            return None
        point = {
            "env_steps": steps,
            "expert_queries": len(setup.buffer),
            "raw": setup.score(learner),
        }
        points.append(point)
        log(f"  {task_name} {method} seed {seed}: {steps} env steps, raw {point['raw']:.3f} "
            f"({time.perf_counter() - t0:.0f} s)")  # fmt: skip
        return point

    config = adversarial_config(method, budget, cfg, seed)
    if method == "gail":
        result = gail(setup.env, setup.learner, setup.buffer, config, on_round=on_round)
    else:
        result, _ = airl(setup.env, setup.learner, setup.buffer, config, on_round=on_round)
    for env in setup.envs:
        env.close()
    return {"task": task_name, "method": method, "seed": seed, "points": points,
            "env_steps": result.env_steps, "expert_queries": result.expert_queries,
            "demo_transitions": result.expert_transitions,
            "seconds": time.perf_counter() - t0}  # fmt: skip


def irl_cell(seed: int, cfg: Config) -> dict:
    """Exact MaxEnt IRL on the seed's FrozenLake demonstration; greedy plan scored exactly."""
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    task = lake_task(cfg)
    buffer = lake_demonstration(task, seed)
    demos = Demonstrations.from_rows(task.mdp, buffer.data)
    fit = maxent_irl(task.mdp, demos, next_state_features(task.mdp),
                             steps=cfg.irl_steps, lr=cfg.irl_lr)  # fmt: skip
    greedy = success_probability(task.mdp, fit.greedy(), 100)
    soft = float(time_indexed_state_distributions(task.mdp, fit.policy)[-1][task.mdp.goal].sum())
    point = {"env_steps": 0, "expert_queries": len(buffer), "raw": greedy}
    return {"task": LAKE, "method": "irl", "seed": seed, "points": [point],
            "soft_policy_success": soft, "seconds": time.perf_counter() - t0}  # fmt: skip


def run_cell(cell: tuple) -> dict:
    """One cell by its description ``(task, method, seed, cfg)``."""
    task_name, method, seed, cfg = cell
    if method == "reference":
        return reference_cell(task_name, seed, cfg)
    if method == "dagger":
        return dagger_cell(task_name, seed, cfg)
    if method == "irl":
        return irl_cell(seed, cfg)
    return adversarial_cell(task_name, method, seed, cfg)


# --------------------------------------------------------------------------- run
def log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def cells_of(tasks: list[str], methods: list[str], cfg: Config) -> list[tuple]:
    """Every cell: references first, then per seed the costly methods (long ones first)."""
    out = [(t, "reference", s, cfg) for t in tasks for s in range(cfg.seeds)]
    for method in ("gail", "airl", "dagger", "irl"):
        if method not in methods:
            continue
        for t in tasks:
            if method == "irl" and t != LAKE:
                continue
            out += [(t, method, s, cfg) for s in range(cfg.seeds)]
    return out


def run(cfg: Config, tasks: list[str], methods: list[str], jobs: int = 1) -> dict:
    """Every cell (``jobs`` processes); the raw rows, the budgets, the wall time."""
    t_start = time.perf_counter()
    cells = cells_of(tasks, methods, cfg)
    rows: list[dict] = []

    def done(cell: tuple, row: dict) -> None:
        rows.append(row)
        last = row["points"][-1]["raw"] if "points" in row else row["expert"]
        log(f"[{len(rows)}/{len(cells)}] {cell[0]} {cell[1]} seed {cell[2]}: {last:.3f} "
            f"(total {time.perf_counter() - t_start:.0f} s)")  # fmt: skip

    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            futures = {pool.submit(run_cell, cell): cell for cell in cells}
            for future in as_completed(futures):
                done(futures[future], future.result())
    else:
        for cell in cells:
            done(cell, run_cell(cell))
    order = {(c[0], c[1], c[2]): i for i, c in enumerate(cells)}
    rows.sort(key=lambda r: order[(r["task"], r["method"], r["seed"])])
    return {
        "config": dataclasses.asdict(cfg),
        "tasks": tasks,
        "methods": methods,
        "jobs": jobs,
        "budgets": {t: dataclasses.asdict(adversarial_budget(t, cfg)) for t in tasks},
        "demonstrations": {
            t: ("1 episode, first 25 steps" if t == "CartPole-v1" else "1 episode") for t in tasks
        },
        "rows": rows,
        "seconds": time.perf_counter() - t_start,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = _report.parser(__doc__)
    parser.add_argument("--seeds", type=int, default=None, help="training seeds per task")
    parser.add_argument("--tasks", nargs="+", default=list(TASK_NAMES), choices=TASK_NAMES)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (same results)")
    parser.add_argument(
        "--adversarial-steps", type=int, default=None, help="GAIL/AIRL budget of every task"
    )
    args = parser.parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    torch.set_num_threads(1)
    cfg = QUICK if args.quick else Config()
    if args.seeds is not None:
        cfg = dataclasses.replace(cfg, seeds=args.seeds)
    if args.adversarial_steps is not None:
        cfg = dataclasses.replace(cfg, adversarial_steps=args.adversarial_steps)
    results = run(cfg, args.tasks, args.methods, jobs=args.jobs)
    results["machine"] = _report.machine()
    figure(results, _report.results_dir(out_dir) / f"{NAME}.png")
    text = markdown(results)
    _report.write(NAME, results, text, out_dir=out_dir)
    print(text)
    return results


if __name__ == "__main__":
    main()

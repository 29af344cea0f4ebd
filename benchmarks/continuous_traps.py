"""Known traps of continuous control on this stack, measured.

1. ``float64``: MuJoCo observations arrive as float64; a float32 policy fails on them
   until ``DoubleToFloat`` (``make_env`` adds it).
2. ``vector_final_obs``: ``GymEnv(id, num_envs=N)`` records zeros as the final
   observation of a lane that ends before the others; ``make_env``'s
   ``GymWrapper(SyncVectorEnv(..., autoreset_mode=DISABLED))`` records the real one.
3. ``frame_skip``: an expert tuned for the env's time step, run with each action
   held for k steps, against the same expert re-identified for the k-step model
   (when its builder takes ``action_repeat``), beside a uniformly random policy
   from the same initial states.
4. ``bang_bang``: DAgger on Pendulum-v1 with a bang-bang swing-up expert; the
   fraction of evaluation episodes still spinning (at least one full turn in the
   last half of the episode) per round, with beta = 0, with beta schedules that
   mix the expert's actions into the rollouts, and with more episodes per round;
   the energy-shaping expert beside them.
5. ``startup``: what ``parallel=True`` (``ParallelEnv``) costs to start and what it
   gains per step against in-process lanes, so users know when it pays: for two
   cheap simulators and for ``CostlyPendulum-v0`` (5 ms of CPU work per step).

    python benchmarks/continuous_traps.py            # refreshes benchmarks/README.md
    python benchmarks/continuous_traps.py --quick    # smoke run, into a temporary directory
    PYTHONPATH=examples python benchmarks/continuous_traps.py --out /tmp/x \\
        --env MountainCarContinuous-v0 --expert mypkg.experts:mountain_car

Every env id is a flag (defaults: the ids of the committed tables): ``--float64-envs``
(trap 1), ``--vector-env`` (2), ``--env`` with ``--expert module:function`` (3; an
env without a built-in expert needs ``--expert``), ``--dagger-env`` (4, an env with
Pendulum-v1's observation ``[cos, sin, velocity]``), ``--startup-envs`` (5).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass

import gymnasium
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv
from torchrl.envs import GymEnv

import _report
from _common import DET, Uniform, accepts, expert_for, reference_returns, rollout, source
from _continuous_traps_report import markdown
from imitrl import keys
from imitrl.algorithms import BCConfig, Constant, DAggerConfig, Exponential, Linear, dagger
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.experts import pendulum_expert
from imitrl.learners import TaskSpec, build
from imitrl.policies import BetaMixer, behaviour_policy

NAME = "continuous_traps"
COSTLY_STEP_S = 5e-3


class CostlyPendulum(PendulumEnv):
    """Pendulum-v1 plus ``COSTLY_STEP_S`` of CPU work per step (an expensive simulator)."""

    def step(self, u):
        end = time.perf_counter() + COSTLY_STEP_S
        while time.perf_counter() < end:
            pass
        return super().step(u)


# make_env("continuous_traps:CostlyPendulum-v0", parallel=True): each worker imports this
# module, which registers the env there too.
if "CostlyPendulum-v0" not in gymnasium.registry:
    gymnasium.register("CostlyPendulum-v0", entry_point=CostlyPendulum, max_episode_steps=200)


@dataclass(frozen=True)
class Config:
    """The whole run."""

    float64_envs: tuple[str, ...] = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5")
    """envs of trap 1"""
    vector_env: str = "CartPole-v1"
    """env of trap 2 (four lanes)"""
    vector_steps: int = 500
    """random-action steps of the 4-lane envs compared in trap 2"""
    async_gymenv: bool = True
    """also build GymEnv(id, num_envs=4) in trap 2 (4 processes; the smoke run skips it)"""
    frame_skip_envs: tuple[str, ...] = (
        "Pendulum-v1",
        "InvertedPendulum-v5",
        "InvertedDoublePendulum-v5",
    )
    """envs of trap 3"""
    frame_skip_expert: str | None = None
    """trap 3's expert as ``module:function`` (one env); None: the envs' built-in experts"""
    frame_skips: tuple[int, ...] = (1, 2, 4)
    """action repeats of trap 3"""
    frame_skip_episodes: int = 5
    """episodes per (env, repeat, policy) in trap 3"""
    dagger_env: str = "Pendulum-v1"
    """env of trap 4 (observation [cos, sin, velocity], Pendulum-v1's experts)"""
    seeds: int = 5
    """DAgger seeds per configuration in trap 4"""
    relabel_rounds: int = 4
    """DAgger rounds after the BC fit in trap 4"""
    episodes_per_round: int = 4
    """Pendulum episodes relabelled per round in trap 4 (small, so that the trap shows)"""
    fit_steps: int = 1000
    """Adam steps per fit in trap 4"""
    eval_episodes: int = 50
    """evaluation episodes per learner in trap 4"""
    startup_envs: tuple[str, ...] = (
        "Pendulum-v1",
        "InvertedDoublePendulum-v5",
        f"{NAME}:CostlyPendulum-v0",
    )
    """envs of trap 5"""
    startup_lanes: tuple[int, ...] = (2, 4)
    """lane counts of trap 5"""
    startup_steps: int = 500
    """batched steps timed per env in trap 5"""
    max_episode_steps: int | None = None
    """override time limits (the smoke run)"""


QUICK = Config(
    vector_steps=60,
    frame_skips=(1, 2),
    frame_skip_episodes=1,
    seeds=1,
    relabel_rounds=1,
    fit_steps=5,
    eval_episodes=2,
    async_gymenv=False,
    startup_lanes=(),
    startup_steps=5,
    max_episode_steps=30,
)


# ------------------------------------------------------------------------- trap 1
def float64_trap(cfg: Config) -> dict:
    out = {}
    for env_id in cfg.float64_envs:
        raw = GymEnv(env_id)
        raw.set_seed(0)
        td = raw.reset()
        dim = td.get(keys.OBSERVATION).shape[-1]
        learner = build(
            "for_env", TaskSpec.from_specs(dim, raw.action_spec)
        )  # the action's default head
        try:
            learner.policy(td)
            error = None
        except RuntimeError as err:
            error = f"{type(err).__name__}: {str(err).splitlines()[0][:80]}"
        fixed = make_env(env_id, seed=0)
        learner.policy(fixed.reset())  # runs
        out[env_id] = {
            "gymenv_dtype": str(td.get(keys.OBSERVATION).dtype),
            "float32_policy_on_gymenv": error,
            "make_env_dtype": str(fixed.observation_spec[keys.OBSERVATION].dtype),
        }
        raw.close()
    return out


# ------------------------------------------------------------------------- trap 2
def _final_obs(env, steps: int) -> dict:
    policy = Uniform(env.action_spec_unbatched, seed=0)
    td = env.reset()
    ends = zeros = 0
    lanes = env.batch_size[0]
    for _ in range(steps):
        out, td = env.step_and_maybe_reset(policy(td))
        done = out.get((keys.NEXT, keys.DONE)).reshape(lanes)
        final = out.get((keys.NEXT, keys.OBSERVATION))[done]
        ends += int(done.sum())
        zeros += int((final == 0).all(-1).sum())
    return {"episode_ends": ends, "all_zero_final_obs": zeros}


def vector_trap(cfg: Config) -> dict:
    out = {}
    if cfg.async_gymenv:
        t0 = time.perf_counter()
        env = GymEnv(cfg.vector_env, num_envs=4, categorical_action_encoding=True)
        env.set_seed(0)
        build = time.perf_counter() - t0
        out["GymEnv(num_envs=4)"] = {"build_s": build, **_final_obs(env, cfg.vector_steps)}
        env.close()
    t0 = time.perf_counter()
    env = make_env(cfg.vector_env, seed=0, num_envs=4)
    build = time.perf_counter() - t0
    out["make_env(num_envs=4)"] = {"build_s": build, **_final_obs(env, cfg.vector_steps)}
    env.close()
    return out


# ------------------------------------------------------------------------- trap 3
def frame_skip_trap(cfg: Config) -> dict:
    """Per env and repeat k: the one-step expert, the expert re-identified for k steps
    (if its builder takes ``action_repeat``) and uniform random actions, all from the
    same initial states."""
    out = {}
    for env_id in cfg.frame_skip_envs:
        build = expert_for(env_id, cfg.frame_skip_expert)
        rows = {}
        for k in cfg.frame_skips:
            env = make_env(env_id, seed=0, frame_skip=k, max_episode_steps=cfg.max_episode_steps)
            n = cfg.frame_skip_episodes
            ref = reference_returns(env, build(), n, seed=0, max_steps=100_000)
            entry = {"one-step expert": float(ref["expert"].mean())}
            if accepts(build, "action_repeat") and k > 1:
                again = reference_returns(env, build(action_repeat=k), n, seed=0, max_steps=100_000)
                entry["re-identified for k steps"] = float(again["expert"].mean())
            entry["uniform random"] = float(ref["random"].mean())
            rows[str(k)] = entry
            env.close()
        out[env_id] = rows
    return out


# ------------------------------------------------------------------------- trap 4
def _spinning(rows, episodes: int) -> float:
    """Fraction of episodes with at least one full turn in their second half."""
    obs = rows.get(keys.OBSERVATION).double()
    theta = torch.atan2(obs[:, 1], obs[:, 0])
    episode, step = rows.get(keys.EPISODE), rows.get(keys.STEP)
    spins = 0
    for e in episode.unique():
        th = theta[episode == e][torch.argsort(step[episode == e])]
        half = th[th.numel() // 2 :]
        d = torch.remainder(half.diff() + math.pi, 2 * math.pi) - math.pi  # wrapped increments
        spins += bool(d.sum().abs() >= 2 * math.pi)
    return spins / episodes


BANG_BANG_CONFIGS = {
    "bang-bang, beta = 0": ("bang_bang", Constant(0.0), 1),
    "bang-bang, beta_i = 0.5^(i-1)": ("bang_bang", Exponential(0.5), 1),
    "bang-bang, beta_i = 1 - i/5": ("bang_bang", Linear(5), 1),
    "bang-bang, beta = 0.5": ("bang_bang", Constant(0.5), 1),
    "bang-bang, beta = 0, 5x episodes per round": ("bang_bang", Constant(0.0), 5),
    "energy-shaping, beta = 0": ("energy", Constant(0.0), 1),
}
"""trap 4: swing-up law, beta schedule, multiple of Config.episodes_per_round"""


def bang_bang_seed(cfg: Config, swing_up: str, beta, per_round: int, seed: int) -> dict:
    """One DAgger run of trap 4: per round, the fraction of evaluation episodes spinning
    and the mean return (the learner alone, beta = 0)."""
    env_id, steps = cfg.dagger_env, cfg.max_episode_steps
    expert = pendulum_expert(swing_up=swing_up)
    demo_env = make_env(env_id, seed=seed, max_episode_steps=steps)
    buffer = DemonstrationBuffer()
    buffer.extend(rollout(demo_env, expert.as_actor(), 1, exploration=DET, max_steps=1000))
    env = make_env(env_id, seed=1000 + seed, num_envs=per_round, max_episode_steps=steps)
    n = cfg.eval_episodes
    eval_env = make_env(env_id, seed=10_000 + seed, num_envs=n, max_episode_steps=steps)
    record = {"spinning": [], "return": []}

    def on_fit(k, learner):
        eval_env.set_seed(10_000 + seed)
        learner_only = behaviour_policy(expert, learner.policy, BetaMixer(0.0))
        rows = rollout(eval_env, learner_only, n, exploration=DET, max_steps=1000)
        record["spinning"].append(_spinning(rows, n))
        record["return"].append(float(rows.get((keys.NEXT, keys.REWARD)).sum() / n))

    dagger(
        source(env, exploration=DET, max_steps=1000),
        expert,
        lambda: build("for_env", env, head="deterministic", loss="mse", seed=seed),
        buffer,
        DAggerConfig(
            rounds=cfg.relabel_rounds + 1,
            episodes_per_round=per_round,
            beta=beta,
            bc=BCConfig(num_steps=cfg.fit_steps, batch_size=256, seed=seed),
            seed=seed,
        ),
        on_fit=on_fit,
    )
    return record


def bang_bang_trap(cfg: Config, configs: dict = BANG_BANG_CONFIGS) -> dict:
    out = {}
    for name, (swing_up, beta, factor) in configs.items():
        seeds = []
        for seed in range(cfg.seeds):
            record = bang_bang_seed(cfg, swing_up, beta, cfg.episodes_per_round * factor, seed)
            seeds.append(record)
            print(f"{name} seed {seed}: {record}", file=sys.stderr, flush=True)
        out[name] = seeds
    return out


# ------------------------------------------------------------------------- trap 5
def startup_cost(cfg: Config) -> dict:
    out = {}
    for env_id in cfg.startup_envs:
        for lanes in cfg.startup_lanes:
            for parallel in (False, True):
                t0 = time.perf_counter()
                env = make_env(env_id, seed=0, num_envs=lanes, parallel=parallel)
                td = env.reset()
                start = time.perf_counter() - t0
                spec = env.action_spec
                t0 = time.perf_counter()
                for _ in range(cfg.startup_steps):
                    td.set(keys.ACTION, spec.zero())
                    _, td = env.step_and_maybe_reset(td)
                run = time.perf_counter() - t0
                t0 = time.perf_counter()
                env.close()
                close = time.perf_counter() - t0
                label = f"{_report.env_label(env_id)} x{lanes}"
                out[f"{label} {'parallel' if parallel else 'in-process'}"] = {
                    "start_s": start,
                    "close_s": close,
                    "frames_per_s": lanes * cfg.startup_steps / run,
                }
    return out


# ---------------------------------------------------------------------------- run
def run(cfg: Config) -> dict:
    t0 = time.perf_counter()
    results = {"config": dataclasses.asdict(cfg), "costly_step_s": COSTLY_STEP_S}
    results["float64"] = float64_trap(cfg)
    results["vector_final_obs"] = vector_trap(cfg)
    results["frame_skip"] = frame_skip_trap(cfg)
    results["bang_bang"] = bang_bang_trap(cfg)
    results["startup"] = startup_cost(cfg)
    results["seconds"] = time.perf_counter() - t0
    return results


def main(argv: list[str] | None = None) -> dict:
    parser = _report.parser(__doc__)
    default = Config()
    parser.add_argument("--float64-envs", nargs="+", default=list(default.float64_envs))
    parser.add_argument("--vector-env", default=default.vector_env)
    parser.add_argument(
        "--env",
        action="append",
        default=None,
        metavar="ID",
        help=f"env of trap 3, repeatable (default: {' '.join(default.frame_skip_envs)})",
    )
    parser.add_argument(
        "--expert", default=None, metavar="MODULE:FUNCTION", help="trap 3's expert (one --env)"
    )
    parser.add_argument("--dagger-env", default=default.dagger_env)
    parser.add_argument("--startup-envs", nargs="+", default=list(default.startup_envs))
    args = parser.parse_args(argv)
    args.env = args.env or list(default.frame_skip_envs)
    if args.expert is not None and len(args.env) != 1:
        parser.error("--expert labels one env: give exactly one --env with it")
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    torch.set_num_threads(1)
    cfg = dataclasses.replace(
        QUICK if args.quick else default,
        float64_envs=tuple(args.float64_envs),
        vector_env=args.vector_env,
        frame_skip_envs=tuple(args.env),
        frame_skip_expert=args.expert,
        dagger_env=args.dagger_env,
        startup_envs=tuple(args.startup_envs),
    )
    results = run(cfg)
    _report.write(NAME, results, markdown(results, cfg), out_dir=out_dir)
    print(markdown(results, cfg))
    return results


if __name__ == "__main__":
    main()

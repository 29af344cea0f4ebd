"""Known traps of continuous control on this stack, measured.

1. ``float64``: MuJoCo observations arrive as float64; a float32 policy fails on them
   until ``DoubleToFloat`` (``make_env`` adds it).
2. ``vector_final_obs``: ``GymEnv(id, num_envs=N)`` records zeros as the final
   observation of a lane that ends before the others; ``make_env``'s
   ``GymWrapper(SyncVectorEnv(..., autoreset_mode=DISABLED))`` records the real one.
3. ``frame_skip``: an expert tuned for the env's time step, run with each action
   held for k steps, against the same expert re-identified for the k-step model.
4. ``bang_bang``: DAgger on Pendulum-v1 with a bang-bang swing-up expert; the
   fraction of evaluation episodes still spinning (at least one full turn in the
   last half of the episode) per round, with beta = 0, with beta schedules that
   mix the expert's actions into the rollouts, and with more episodes per round;
   the energy-shaping expert beside them.
5. ``startup``: what ``parallel=True`` (``ParallelEnv``) costs to start and what it
   gains per step against in-process lanes, so users know when it pays: for two
   cheap simulators and for ``CostlyPendulum-v0`` (5 ms of CPU work per step).

    python benchmarks/continuous_traps.py            # refreshes benchmarks/README.md
    python benchmarks/continuous_traps.py --quick --out /tmp/smoke
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv
from torchrl.envs import GymEnv
from torchrl.envs.utils import ExplorationType

import _report
from bc_vs_dagger import t_interval
from imitrl import keys
from imitrl.algorithms import (
    BCConfig,
    Constant,
    DAggerConfig,
    EnvSource,
    Exponential,
    Linear,
    dagger,
)
from imitrl.data import DemonstrationBuffer, rollout_episodes
from imitrl.envs import make_env
from imitrl.evaluation import evaluate
from imitrl.experts import (
    inverted_double_pendulum_expert,
    inverted_pendulum_expert,
    pendulum_expert,
)
from imitrl.policies import ActorCritic, BetaMixer, behaviour_policy

NAME = "continuous_traps"
DET = ExplorationType.DETERMINISTIC
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

    vector_steps: int = 500
    """random-action steps of the 4-lane CartPole envs compared in trap 2"""
    async_gymenv: bool = True
    """also build GymEnv(id, num_envs=4) in trap 2 (4 processes; the smoke run skips it)"""
    frame_skips: tuple[int, ...] = (1, 2, 4)
    """action repeats of trap 3"""
    frame_skip_episodes: int = 5
    """episodes per (env, repeat, expert) in trap 3"""
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
def float64_trap() -> dict:
    out = {}
    for env_id in ("InvertedPendulum-v5", "InvertedDoublePendulum-v5"):
        raw = GymEnv(env_id)
        raw.set_seed(0)
        td = raw.reset()
        dim = td.get(keys.OBSERVATION).shape[-1]
        learner = ActorCritic.mlp(dim, raw.action_spec, head="deterministic")
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
    g = torch.Generator().manual_seed(0)
    td = env.reset()
    ends = zeros = 0
    lanes = env.batch_size[0]
    for _ in range(steps):
        td.set(keys.ACTION, torch.randint(0, 2, (lanes,), generator=g))
        out, td = env.step_and_maybe_reset(td)
        done = out.get((keys.NEXT, keys.DONE)).reshape(lanes)
        final = out.get((keys.NEXT, keys.OBSERVATION))[done]
        ends += int(done.sum())
        zeros += int((final == 0).all(-1).sum())
    return {"episode_ends": ends, "all_zero_final_obs": zeros}


def vector_trap(cfg: Config) -> dict:
    out = {}
    if cfg.async_gymenv:
        t0 = time.perf_counter()
        env = GymEnv("CartPole-v1", num_envs=4, categorical_action_encoding=True)
        env.set_seed(0)
        build = time.perf_counter() - t0
        out["GymEnv(num_envs=4)"] = {"build_s": build, **_final_obs(env, cfg.vector_steps)}
        env.close()
    t0 = time.perf_counter()
    env = make_env("CartPole-v1", seed=0, num_envs=4)
    build = time.perf_counter() - t0
    out["make_env(num_envs=4)"] = {"build_s": build, **_final_obs(env, cfg.vector_steps)}
    env.close()
    return out


# ------------------------------------------------------------------------- trap 3
def frame_skip_trap(cfg: Config) -> dict:
    builders = {
        "Pendulum-v1": lambda repeat: pendulum_expert(),
        "InvertedPendulum-v5": lambda repeat: inverted_pendulum_expert(action_repeat=repeat),
        "InvertedDoublePendulum-v5": lambda repeat: inverted_double_pendulum_expert(
            action_repeat=repeat
        ),
    }
    out = {}
    for env_id, build in builders.items():
        rows = {}
        for k in cfg.frame_skips:
            env = make_env(env_id, seed=0, frame_skip=k, max_episode_steps=cfg.max_episode_steps)
            entry = {}
            variants = {"one-step expert": build(1)}
            if env_id != "Pendulum-v1" and k > 1:
                variants["re-identified for k steps"] = build(k)
            for name, expert in variants.items():
                env.set_seed(0)
                ev = evaluate(
                    env,
                    expert.as_actor(),
                    cfg.frame_skip_episodes,
                    exploration=DET,
                    max_steps=100_000,
                )
                entry[name] = ev.mean_return
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


def bang_bang_trap(cfg: Config, configs: dict = BANG_BANG_CONFIGS) -> dict:
    steps = cfg.max_episode_steps
    out = {}
    for name, (swing_up, beta, factor) in configs.items():
        per_round = cfg.episodes_per_round * factor
        expert = pendulum_expert(swing_up=swing_up)
        seeds = []
        for seed in range(cfg.seeds):
            demo_env = make_env("Pendulum-v1", seed=seed, max_episode_steps=steps)
            buffer = DemonstrationBuffer()
            buffer.extend(
                rollout_episodes(demo_env, expert.as_actor(), 1, exploration=DET, max_steps=1000)
            )
            source = make_env(
                "Pendulum-v1",
                seed=1000 + seed,
                num_envs=per_round,
                max_episode_steps=steps,
            )
            eval_env = make_env(
                "Pendulum-v1",
                seed=10_000 + seed,
                num_envs=cfg.eval_episodes,
                max_episode_steps=steps,
            )
            record = {"spinning": [], "return": []}

            def on_fit(k, learner, record=record, eval_env=eval_env, seed=seed, expert=expert):
                eval_env.set_seed(10_000 + seed)
                learner_only = behaviour_policy(expert, learner.policy, BetaMixer(0.0))
                rows = rollout_episodes(
                    eval_env, learner_only, cfg.eval_episodes, exploration=DET, max_steps=1000
                )
                record["spinning"].append(_spinning(rows, cfg.eval_episodes))
                ret = rows.get((keys.NEXT, keys.REWARD)).sum() / cfg.eval_episodes
                record["return"].append(float(ret))

            spec = source.action_spec_unbatched
            dagger(
                EnvSource(source, exploration=DET, max_steps=1000),
                expert,
                lambda spec=spec, seed=seed: ActorCritic.mlp(
                    3, spec, head="deterministic", seed=seed
                ),
                buffer,
                DAggerConfig(
                    rounds=cfg.relabel_rounds + 1,
                    episodes_per_round=per_round,
                    beta=beta,
                    fit=BCConfig(
                        num_steps=cfg.fit_steps, batch_size=256, loss_type="mse", seed=seed
                    ),
                    seed=seed,
                ),
                on_fit=on_fit,
            )
            seeds.append(record)
            print(f"{name} seed {seed}: {record}", file=sys.stderr, flush=True)
        out[name] = seeds
    return out


# ------------------------------------------------------------------------- trap 5
def startup_cost(cfg: Config) -> dict:
    out = {}
    for env_id in ("Pendulum-v1", "InvertedDoublePendulum-v5", f"{NAME}:CostlyPendulum-v0"):
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
                out[f"{env_id} x{lanes} {'parallel' if parallel else 'in-process'}"] = {
                    "start_s": start,
                    "close_s": close,
                    "frames_per_s": lanes * cfg.startup_steps / run,
                }
    return out


# ------------------------------------------------------------------------- report
def markdown(results: dict, cfg: Config) -> str:
    lines = [f"Total time {results['seconds']:.0f} s (1 torch thread).", ""]
    lines += ["**1. float64 observations** (a float32 MLP fed a `GymEnv` observation):", ""]
    rows = [
        [k, v["gymenv_dtype"], f"`{v['float32_policy_on_gymenv']}`", v["make_env_dtype"]]
        for k, v in results["float64"].items()
    ]
    lines += [
        _report.table(["env", "GymEnv obs", "float32 policy on it", "make_env obs"], rows),
        "",
    ]
    lines += [
        f"**2. final observations of vectorised CartPole** (4 lanes, {cfg.vector_steps} "
        "random-action steps):",
        "",
    ]
    rows = [
        [k, v["episode_ends"], v["all_zero_final_obs"], f"{v['build_s']:.1f}"]
        for k, v in results["vector_final_obs"].items()
    ]
    lines += [
        _report.table(["env", "episode ends", "all-zero final observations", "build s"], rows),
        "",
    ]
    lines += [
        f"**3. frame_skip** (each action held k steps; mean return of "
        f"{cfg.frame_skip_episodes} episodes):",
        "",
    ]
    rows = []
    for env_id, per in results["frame_skip"].items():
        for k, entry in per.items():
            rows.append(
                [
                    env_id,
                    k,
                    f"{entry['one-step expert']:.1f}",
                    f"{entry['re-identified for k steps']:.1f}"
                    if "re-identified for k steps" in entry
                    else "-",
                ]
            )
    lines += [
        _report.table(
            ["env", "k", "expert tuned for one step", "LQR re-identified for k steps"], rows
        ),
        "",
    ]
    lines += [
        f"**4. DAgger on Pendulum-v1 with a bang-bang expert** ({cfg.seeds} seeds, one "
        f"demonstration, {cfg.episodes_per_round} episodes per round unless stated, "
        f"{cfg.fit_steps} fit steps, {cfg.eval_episodes} "
        "evaluation episodes; spinning = at least one full turn in the second half of an "
        "episode; mean [95% t-interval over seeds]):",
        "",
    ]
    rows = []
    rounds = cfg.relabel_rounds + 1
    for name, seeds in results["bang_bang"].items():
        spin = [f"{t_interval([s['spinning'][k] for s in seeds])[0]:.2f}" for k in range(rounds)]
        spinning_rounds = sum(x >= 0.2 for s in seeds for x in s["spinning"][1:])
        final = t_interval([s["return"][-1] for s in seeds])
        rows.append(
            [
                name,
                *spin,
                f"{spinning_rounds}/{len(seeds) * (rounds - 1)}",
                f"{sum(s['spinning'][-1] >= 0.2 for s in seeds)}/{len(seeds)}",
                f"{final[0]:.0f} [{final[1]:.0f}, {final[2]:.0f}]",
            ]
        )
    lines += [
        _report.table(
            [
                "expert, beta",
                *[f"spinning r{k}" for k in range(rounds)],
                "(seed, round >= 1) spinning >= 20%",
                f"seeds spinning >= 20% at r{rounds - 1}",
                f"return r{rounds - 1}",
            ],
            rows,
        ),
        "",
    ]
    lines += [
        f"**5. start-up cost of `parallel=True`** ({cfg.startup_steps} batched steps of "
        "zero actions):",
        "",
    ]
    rows, paying = [], []
    for k, v in results["startup"].items():
        pays = "-"
        if k.endswith(" parallel"):
            base = results["startup"][k.replace(" parallel", " in-process")]
            saved = 1 / base["frames_per_s"] - 1 / v["frames_per_s"]  # seconds per frame
            extra = v["start_s"] - base["start_s"]
            pays = f"{extra / saved:.0f}" if saved > 0 else "never (slower per frame)"
            if saved > 0:
                paying.append(k.replace(f"{NAME}:", "").replace(" parallel", ""))
        rows.append(
            [
                k.replace(f"{NAME}:", ""),
                f"{v['start_s']:.2f}",
                f"{v['close_s']:.2f}",
                f"{v['frames_per_s']:.0f}",
                pays,
            ]
        )
    lines += [
        _report.table(
            ["env x lanes", "start s", "close s", "frames/s", "pays after (frames)"], rows
        ),
        "",
        f"CostlyPendulum-v0 is Pendulum-v1 with {COSTLY_STEP_S * 1e3:.0f} ms of CPU work per "
        "step, a stand-in for an expensive simulator. "
        + (
            f"Here `parallel=True` paid off only for: {', '.join(paying)}."
            if paying
            else "Here `parallel=True` never paid off: the inter-process round trip cost "
            "more than it saved (on a 2-core machine the workers also compete with the "
            "main process); keep `parallel=False` unless a step costs far more and idle "
            "cores are available."
        ),
    ]
    return "\n".join(lines)


def run(cfg: Config) -> dict:
    t0 = time.perf_counter()
    results = {"config": dataclasses.asdict(cfg)}
    results["float64"] = float64_trap()
    results["vector_final_obs"] = vector_trap(cfg)
    results["frame_skip"] = frame_skip_trap(cfg)
    results["bang_bang"] = bang_bang_trap(cfg)
    results["startup"] = startup_cost(cfg)
    results["seconds"] = time.perf_counter() - t0
    return results


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run on a tiny budget")
    parser.add_argument("--out", type=Path, default=None, help="write here, not to the README")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cfg = QUICK if args.quick else Config()
    results = run(cfg)
    _report.write(NAME, results, markdown(results, cfg), out_dir=args.out)
    print(markdown(results, cfg))
    return results


if __name__ == "__main__":
    main()

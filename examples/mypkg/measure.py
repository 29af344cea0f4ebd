"""Measure the scripted experts in :mod:`mypkg.experts` with plain gymnasium.

Runs each expert for ``--episodes`` episodes (seeds ``--seed`` .. ``--seed + episodes
- 1``, one ``env.reset(seed=...)`` per episode) and prints the mean/std/min/max
return, the episode lengths and, for the continuous-action envs, the fraction of
actions exactly at the action bounds. Before that it checks that the LunarLander
ports give exactly gymnasium's own ``heuristic`` action (numpy and torch inputs,
single and batched) on a few hundred observations.

    .venv/bin/python examples/mypkg/measure.py            # all four experts
    .venv/bin/python examples/mypkg/measure.py --env Reacher-v5 --lengths

Needs ``gymnasium[box2d]`` (LunarLander) and ``gymnasium[mujoco]`` (Reacher).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import torch

ENVS = {
    "MountainCarContinuous-v0": "mountain_car",
    "LunarLanderContinuous-v3": "lunar_lander_continuous",
    "LunarLander-v3": "lunar_lander",
    "Reacher-v5": "reacher",
}


def _experts():
    try:
        from mypkg import experts
    except ImportError:  # run as a script from anywhere: put examples/ on the path
        sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
        from mypkg import experts
    return experts


def run_episodes(env_id: str, fn, seeds) -> dict:
    env = gym.make(env_id)
    box = isinstance(env.action_space, gym.spaces.Box)
    returns, lengths, at_bound, n_actions = [], [], 0, 0
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        ret, steps, done = 0.0, 0, False
        while not done:
            action = np.asarray(fn(obs))
            if box:
                at_bound += int(
                    np.sum((action == env.action_space.low) | (action == env.action_space.high))
                )
                n_actions += action.size
            else:
                action = int(action)
            obs, reward, terminated, truncated, _ = env.step(action)
            ret += float(reward)
            steps += 1
            done = terminated or truncated
        returns.append(ret)
        lengths.append(steps)
    env.close()
    return {
        "returns": np.array(returns),
        "lengths": np.array(lengths),
        "bound_frac": at_bound / n_actions if box else None,
    }


def check_lunar_heuristic(n_episodes: int = 4, seed: int = 1000) -> None:
    """Our ports vs ``gymnasium.envs.box2d.lunar_lander.heuristic``, action by action.

    Observations come from rollouts of the heuristic itself (landings, leg contacts)
    and of random actions (crashes, large angles), plus random synthetic ones.
    """
    from gymnasium.envs.box2d.lunar_lander import heuristic

    experts = _experts()
    rng = np.random.default_rng(seed)
    observations = []
    for env_id in ("LunarLander-v3", "LunarLanderContinuous-v3"):
        env = gym.make(env_id)
        env.action_space.seed(seed)
        for i in range(n_episodes):
            obs, _ = env.reset(seed=seed + i)
            use_random, done = i % 2 == 1, False
            while not done:
                observations.append(obs)
                action = env.action_space.sample() if use_random else heuristic(env, obs)
                obs, _, terminated, truncated, _ = env.step(action)
                done = terminated or truncated
        env.close()
    synthetic = rng.normal(scale=0.5, size=(300, 8)).astype(np.float32)
    synthetic[:, 6:] = rng.integers(0, 2, size=(300, 2))
    obs = np.concatenate([np.stack(observations), synthetic]).astype(np.float32)

    for continuous, fn in ((True, experts.lunar_lander_continuous), (False, experts.lunar_lander)):
        fake_env = SimpleNamespace(unwrapped=SimpleNamespace(continuous=continuous))
        ref = np.stack([np.asarray(heuristic(fake_env, o)) for o in obs])
        single = np.stack([np.asarray(fn(o)) for o in obs])
        batched = np.asarray(fn(obs))
        batched_torch = fn(torch.from_numpy(obs)).numpy()
        nested = np.asarray(fn(obs[: len(obs) // 2 * 2].reshape(2, -1, 8))).reshape(
            -1, *ref.shape[1:]
        )
        for name, got in (
            ("single", single),
            ("batched numpy", batched),
            ("batched torch", batched_torch),
        ):
            mismatches = int(np.sum(np.any((got != ref).reshape(len(obs), -1), axis=-1)))
            if mismatches:
                raise AssertionError(f"{fn.__name__} ({name}): {mismatches} mismatches")
        if not np.array_equal(nested, ref[: len(nested)]):
            raise AssertionError(f"{fn.__name__} ([2, N, 8] input): mismatch")
        contact = int(np.sum(obs[:, 6:].any(-1)))
        print(
            f"{fn.__name__}: identical to gymnasium's heuristic on {len(obs)} observations "
            f"({contact} with leg contact; single, batched numpy, batched torch, [2, N, 8])"
        )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", action="append", choices=list(ENVS), help="default: all")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0, help="first seed")
    parser.add_argument("--lengths", action="store_true", help="print every episode length")
    parser.add_argument("--no-check", action="store_true", help="skip the heuristic check")
    args = parser.parse_args(argv)

    experts = _experts()
    env_ids = args.env or list(ENVS)
    if not args.no_check and any(e.startswith("LunarLander") for e in env_ids):
        check_lunar_heuristic()
        print()

    seeds = range(args.seed, args.seed + args.episodes)
    header = (
        f"{'env':<26}{'expert':<25}{'return mean':>12}{'std':>8}{'min':>9}{'max':>9}"
        f"{'len mean':>10}{'len min':>8}{'len max':>8}{'at bound':>10}{'time':>7}"
    )
    print(f"{args.episodes} episodes, seeds {seeds.start}..{seeds.stop - 1}")
    print(header)
    print("-" * len(header))
    rows = []
    for env_id in env_ids:
        fn = getattr(experts, ENVS[env_id])
        start = time.perf_counter()
        res = run_episodes(env_id, fn, seeds)
        elapsed = time.perf_counter() - start
        r, n = res["returns"], res["lengths"]
        bound = "-" if res["bound_frac"] is None else f"{res['bound_frac']:.3f}"
        print(
            f"{env_id:<26}{fn.__name__:<25}{r.mean():>12.2f}{r.std():>8.2f}{r.min():>9.2f}"
            f"{r.max():>9.2f}{n.mean():>10.1f}{n.min():>8d}{n.max():>8d}{bound:>10}"
            f"{elapsed:>6.1f}s"
        )
        rows.append((env_id, n))
    if args.lengths:
        print()
        for env_id, n in rows:
            print(f"{env_id} lengths: {n.tolist()}")


if __name__ == "__main__":
    main()

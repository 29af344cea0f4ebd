"""Snapshot (issue 46): an env's state taken, steps played, the state put back: the same
steps then give the same observations, rewards and flags, bit for bit; classic control,
MuJoCo, Meta-World (all 50 tasks with -m slow), imitrl's own envs; envs in other
processes refused."""

from __future__ import annotations

import functools

import pytest
import torch

from imitrl import keys
from imitrl.envs import make_env
from imitrl.envs.snapshot import Snapshot


def _steps(env, td, actions) -> list:
    out = []
    for action in actions:
        step = env.step(td.clone().set(keys.ACTION, action))
        out.append(step.get(keys.NEXT).exclude("step_count"))
        td = step.get(keys.NEXT)
    return out


def _restores_exactly(env, seed: int = 0, ahead: int = 20) -> bool:
    torch.manual_seed(seed)
    td = env.reset()
    for _ in range(3):
        td = env.step(env.rand_action(td)).get(keys.NEXT)
    actions = [env.rand_action(td.clone()).get(keys.ACTION) for _ in range(ahead)]
    snapshot = Snapshot.take(env)
    first = _steps(env, td, actions)
    _steps(env, first[-1], actions[:5])  # wander off, further
    snapshot.restore()
    again = _steps(env, td, actions)
    return all((a == b).all() for a, b in zip(first, again))


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1", "FrozenLake-v1", "Acrobot-v1"])
def test_classic_control_steps_again_as_it_did(env_id):
    assert _restores_exactly(make_env(env_id, seed=1, max_episode_steps=500))


@pytest.mark.parametrize("env_id", ["Hopper-v5", "Ant-v5"])
def test_mujoco_steps_again_as_it_did(env_id):
    pytest.importorskip("mujoco")
    assert _restores_exactly(make_env(env_id, seed=1))


@pytest.mark.parametrize(
    "tasks",
    [("reach-v3", "pick-place-v3", "door-open-v3"),
     pytest.param("MT50", marks=pytest.mark.slow)],  # all 50: 11 s, with -m slow
)  # fmt: skip
def test_metaworld_tasks_step_again_as_they_did(tasks):
    pytest.importorskip("metaworld")
    from imitrl.envs.metaworld import MT50

    bad = []
    for task in MT50 if tasks == "MT50" else tasks:
        env = make_env(f"metaworld/{task}", seed=2)
        if not _restores_exactly(env, ahead=10):
            bad.append(task)
        env.close()
    assert bad == []


@pytest.mark.parametrize("rng", ["torch", "gymnasium"])
def test_imitrls_own_envs_step_again_as_they_did(lake, rng):
    from imitrl.envs import TabularEnv
    from imitrl.envs.multimodal import TwoWayObstacleEnv

    assert _restores_exactly(TwoWayObstacleEnv(seed=4))
    assert _restores_exactly(TabularEnv(lake, rng=rng, seed=5))


def test_a_snapshot_without_restore_changes_nothing_and_others_are_refused():
    env = make_env("Pendulum-v1", seed=3)
    td = env.reset()
    action = env.rand_action(td.clone()).get(keys.ACTION)
    want = _steps(env, td, [action])[0]
    env2 = make_env("Pendulum-v1", seed=3)
    td2 = env2.reset()
    Snapshot.take(env2)
    assert (_steps(env2, td2, [action])[0] == want).all()
    from torchrl.envs import ParallelEnv

    parallel = ParallelEnv(1, functools.partial(make_env, "Pendulum-v1", seed=0))
    with pytest.raises(ValueError, match="cannot be taken"):
        Snapshot.take(parallel)  # its state is in its worker (never started here)

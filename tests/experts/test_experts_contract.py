"""One expert type: casts to the action spec, the same object in every rollout, the one action check."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Unbounded
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger
from imitrl.data import DemonstrationBuffer
from imitrl.envs import TabularEnv
from imitrl.envs.multimodal import TwoWayObstacleEnv, two_way_expert
from imitrl.evaluation import evaluate
from imitrl.experts import acrobot_expert, cartpole_expert, mountaincar_expert, pendulum_expert
from imitrl.learners import TaskSpec, build
from imitrl.policies import Expert, as_actor
from imitrl.policies.action_check import cast_action, check_action
from imitrl.runtime import episode_returns, rollout_episodes

BOX = Bounded(-2.0, 2.0, shape=(1,), dtype=torch.float32)  # one lane's continuous spec
DISCRETE = Categorical(4, shape=(), dtype=torch.int64)


def _obs(n: int = 8, d: int = 3) -> TensorDict:
    x = torch.linspace(-1, 1, n * d).reshape(n, d)
    return TensorDict({keys.OBSERVATION: x}, [n])


# --------------------------------------------------------------------------- casts
def test_float64_numpy_output_is_cast_to_float32_when_exact():
    expert = Expert.from_callable(
        lambda obs: np.asarray(obs[..., :1], dtype=np.float64) * 0.1, action_spec=BOX
    )
    td = expert(_obs())
    label = td.get(keys.EXPERT_ACTION)
    assert label.dtype == torch.float32 and label.shape == (8, 1)
    assert torch.equal(label, (_obs().get(keys.OBSERVATION)[:, :1].double() * 0.1).float())


def test_missing_trailing_action_dimension_is_added():
    expert = Expert.from_callable(lambda obs: obs.sum(-1).double() / 10, action_spec=BOX)
    label = expert(_obs()).get(keys.EXPERT_ACTION)
    assert label.shape == (8, 1) and label.dtype == torch.float32
    one = Expert.from_callable(lambda obs: 0.25, action_spec=BOX)  # python float, unbatched
    assert one(TensorDict({keys.OBSERVATION: torch.zeros(3)}, [])).get(
        keys.EXPERT_ACTION
    ).tolist() == [0.25]


def test_python_and_numpy_ints_become_int64():
    expert = Expert.from_callable(
        lambda obs: (np.asarray(obs[:, 0]) > 0).astype(np.int32) * 3, action_spec=DISCRETE
    )
    label = expert(_obs()).get(keys.EXPERT_ACTION)
    assert label.dtype == torch.int64 and label.tolist() == [0, 0, 0, 0, 3, 3, 3, 3]
    single = Expert.from_callable(lambda obs: 2, action_spec=DISCRETE)
    assert single(TensorDict({keys.OBSERVATION: torch.zeros(3)}, [])).get(
        keys.EXPERT_ACTION
    ).dtype == (torch.int64)


@pytest.mark.parametrize(
    ("fn", "spec", "returned", "needed"),
    [
        (
            lambda obs: np.full(obs.shape[:1], 1e300),
            BOX,
            r"torch.float64, shape \(8,\)",
            r"\(8, 1\)",
        ),
        (
            lambda obs: np.full(obs.shape[:1], 0.5),
            DISCRETE,
            r"torch.float64, shape \(8,\)",
            r"\(8,\)",
        ),
        (lambda obs: torch.zeros(8, 2), BOX, r"torch.float32, shape \(8, 2\)", r"\(8, 1\)"),
        (
            lambda obs: torch.zeros(8, 1, dtype=torch.int64),
            DISCRETE,
            r"torch.int64, shape \(8, 1\)",
            r"\(8,\)",
        ),
    ],
    ids=["overflow", "half-into-int", "width-2-for-1", "extra-dim"],
)
def test_inexact_casts_are_refused_naming_both_sides(fn, spec, returned, needed):
    expert = Expert.from_callable(fn, action_spec=spec)
    with pytest.raises(ValueError, match="returned dtype " + returned) as err:
        expert(_obs())
    assert f"needs dtype {spec.dtype}, shape " in str(err.value)
    assert re.search("needs dtype [^ ]+, shape " + needed, str(err.value))


def test_cast_keeps_whole_floats_and_refuses_nan_into_ints():
    spec = Categorical(3, shape=(), dtype=torch.int64)
    out = cast_action(np.array([0.0, 2.0]), spec, batch_shape=(2,))
    assert out.dtype == torch.int64 and out.tolist() == [0, 2]
    with pytest.raises(ValueError, match=r"do not fit torch\.int64"):
        cast_action(np.array([0.0, np.nan]), spec, batch_shape=(2,))
    with pytest.raises(ValueError, match=r"do not fit torch\.float32"):
        cast_action(np.array([3.0e38, 4.0e38]), Unbounded(shape=(2,), dtype=torch.float32))
    # below float32's smallest normal number the absolute error is at most 1.2e-38: kept
    assert cast_action(1e-50, Unbounded(shape=(1,), dtype=torch.float32)).tolist() == [0.0]
    with pytest.raises(ValueError, match="not a numeric"):
        cast_action(["a"], spec, batch_shape=(1,))


def test_one_action_check_for_dtype_shape_and_range():
    check_action(torch.zeros(5, 1), BOX, batch_shape=(5,), in_range=True)
    with pytest.raises(ValueError, match=r"dtype torch.float64, shape \(5, 1\); the action spec"):
        check_action(torch.zeros(5, 1, dtype=torch.float64), BOX, batch_shape=(5,))
    with pytest.raises(ValueError, match="outside the bounds"):
        check_action(torch.full((5, 1), 3.0), BOX, batch_shape=(5,), in_range=True)
    check_action(torch.full((5, 1), 3.0), BOX, batch_shape=(5,))  # range only on request
    with pytest.raises(ValueError, match=r"action 4, outside \[0, 4\)"):
        check_action(torch.tensor([0, 4]), DISCRETE, batch_shape=(2,), in_range=True)


# ---------------------------------------------------------------------- the one type
def test_every_builder_returns_an_expert(lake):
    learner = build("cross_entropy", TaskSpec(action=2, num_states=4))
    built = [
        Expert.from_table(torch.tensor([0, 1])),
        Expert.from_q(torch.eye(2)),
        Expert.from_callable(lambda obs: obs),
        Expert.from_policy(learner.policy),
        two_way_expert(),
        cartpole_expert(),
        mountaincar_expert(),
        acrobot_expert(),
        pendulum_expert(),
    ]
    assert all(isinstance(e, Expert) for e in built)
    wrapped = Expert.from_policy(learner.policy)
    out = wrapped(TensorDict({keys.OBSERVATION: torch.arange(4)}, [4]))
    assert out[keys.EXPERT_ACTION].tolist() == [0, 0, 0, 0] and keys.ACTION not in out.keys()


def test_from_policy_expert_drives_an_env_bare(lake):
    env = TabularEnv(lake, batch_size=(4,), seed=0)
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))  # greedy: LEFT everywhere
    rows = rollout_episodes(env, Expert.from_policy(learner.policy), 4)
    assert (rows[keys.ACTION] == 0).all() and rows[keys.EXPERT_EXECUTED].all()


def test_the_same_expert_in_rollouts_evaluation_and_dagger(lake, expert_table):
    expert = Expert.from_table(expert_table)
    env = TabularEnv(lake, batch_size=(4,), seed=0)
    rows = rollout_episodes(env, expert, 6)  # bare: no as_actor(), no exploration
    assert torch.equal(rows[keys.ACTION], expert_table[rows[keys.OBSERVATION]])
    assert expert.action_spec is not None  # bound to the env's spec by its first rollout
    ev = evaluate(env, expert, 400, seed=0)
    assert ev.exploration == "deterministic" and ev.exact_success > 0.7
    summary = episode_returns(env, expert, 8)
    assert summary.returns.shape == (8,)
    source = EnvSource(env, exploration=ExplorationType.DETERMINISTIC)
    demos = source.collect(expert, 3, round_index=0, first_episode=0)
    buffer = DemonstrationBuffer(num_states=16)
    buffer.extend(demos)
    res = dagger(
        source,
        expert,
        lambda: build("cross_entropy", TaskSpec(action=4, num_states=16)),
        buffer,
        DAggerConfig(rounds=2, episodes_per_round=2, bc=BCConfig(num_steps=20)),
    )
    relabelled = res.buffer.data[res.buffer.data[keys.ROUND] == 1]
    assert torch.equal(relabelled[keys.EXPERT_ACTION], expert_table[relabelled[keys.OBSERVATION]])
    # the old spellings still drive an env
    for actor in (expert.as_actor(), as_actor(expert)):
        rows = rollout_episodes(env, actor, 2, exploration=ExplorationType.DETERMINISTIC)
        assert rows[keys.EXPERT_EXECUTED].all()


def test_a_callable_expert_is_cast_at_its_first_rollout():
    # float64 numpy, one number per lane: cast to the env's float32 [N, 1] at the rollout
    expert = Expert.from_callable(lambda obs: np.zeros(obs.shape[:-1]))
    unbound = expert(TensorDict({keys.OBSERVATION: torch.zeros(2, 2)}, [2]))
    assert unbound.get(keys.EXPERT_ACTION).dtype == torch.float64  # no spec yet: as returned
    env = TwoWayObstacleEnv(batch_size=(4,), seed=0)
    rows = rollout_episodes(env, expert, 4, max_steps=100)
    assert rows[keys.EXPERT_ACTION].dtype == torch.float32
    assert rows[keys.EXPERT_ACTION].shape[1:] == (1,)
    with pytest.raises(ValueError, match=r"labels in dtype torch.float32, shape \(1,\)"):
        expert.bind(Categorical(2, shape=(), dtype=torch.int64))


def test_plain_modules_must_state_exploration(lake):
    env = TabularEnv(lake, seed=0)
    with pytest.raises(ValueError, match="exploration is required"):
        rollout_episodes(env, Expert.from_table(torch.zeros(16, dtype=torch.long)).as_actor(), 1)
    with pytest.raises(ValueError, match="Expert or a TensorDict module"):
        rollout_episodes(env, lambda td: td, 1, exploration=ExplorationType.DETERMINISTIC)
    learner = build(
        "cross_entropy", TaskSpec(action=4, num_states=16)
    )  # a Learner acts as its exploration says
    assert evaluate(env, learner, 3).exploration == "deterministic"


def test_a_rollout_policy_that_writes_no_expert_label_is_refused():
    from torchrl.envs.utils import ExplorationType

    from imitrl.envs import make_env
    from imitrl.runtime import rollout_episodes

    env = make_env("CartPole-v1", seed=0)
    learner = build("for_env", env)  # writes "action" only: no label to keep as a row
    with pytest.raises(ValueError, match="must write 'expert_action'"):
        rollout_episodes(env, learner.policy, 1, exploration=ExplorationType.DETERMINISTIC)

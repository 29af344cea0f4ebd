"""Learners from every kind of spec TorchRL builds for gymnasium spaces, and the
observation normaliser: fitted once from the demonstrations, saved with the learner,
never seen by the expert or written to a tensordict."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, MultiCategorical, OneHot, Unbounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.learners import ActorCritic, Learner, TaskSpec, build
from imitrl.policies.specs import action_space

G = torch.Generator().manual_seed(0)


def _rows(obs: torch.Tensor, label: torch.Tensor) -> TensorDict:
    return TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, [obs.shape[0]])


def _greedy(learner: Learner, obs: torch.Tensor) -> torch.Tensor:
    td = TensorDict({keys.OBSERVATION: obs}, [obs.shape[0]])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return learner.policy(td).get(keys.ACTION)


# a labelling rule per action kind: the clone must learn it from 256 rows
def _discrete(obs):  # 3 actions by the sign pattern of two features
    return (obs[:, 0] > 0).long() + (obs[:, 1] > 0).long()


SPECS = {
    "categorical": (Categorical(3), lambda o: _discrete(o)),
    "one_hot": (OneHot(3), lambda o: torch.nn.functional.one_hot(_discrete(o), 3)),
    "multi_categorical": (
        MultiCategorical([2, 3]),
        lambda o: torch.stack([(o[:, 0] > 0).long(), _discrete(o)], -1),
    ),
    "bounded": (Bounded(-1.0, 1.0, shape=(2,)), lambda o: torch.tanh(o[:, :2])),
    "unbounded": (Unbounded(shape=(2,)), lambda o: 3.0 * o[:, :2] - 1.0),
}


@pytest.mark.parametrize("kind", sorted(SPECS))
def test_an_mlp_learner_from_every_action_spec_clones_its_labels(kind):
    spec, rule = SPECS[kind]
    obs_spec = Unbounded(shape=(4,))
    obs = torch.randn(256, 4, generator=G) * torch.tensor([1.0, 1.0, 50.0, 0.01]) + 5.0 * (
        torch.arange(4) == 3
    )
    label = rule(obs).to(spec.dtype)
    learner = build(
        "for_env", TaskSpec.from_specs(obs_spec, spec), hidden=(64, 64), lr=3e-3, seed=0
    )
    fit = fit_bc(learner, _rows(obs, label), BCConfig(num_steps=800, batch_size=64))
    assert torch.isfinite(fit.losses).all()
    pred = _greedy(learner, obs)
    assert pred.dtype == label.dtype and pred.shape == label.shape  # what the env takes
    assert spec.is_in(pred[0])
    if label.dtype.is_floating_point:
        assert float((pred - label).abs().mean()) < 0.1
    else:
        exact = (pred == label).reshape(256, -1).all(-1).float().mean()
        assert float(exact) > 0.9


def test_integer_state_observations_feed_the_mlp_one_hot():
    learner = build("for_env", TaskSpec.from_specs(Categorical(5), 2), seed=0, lr=1e-2)
    obs = torch.arange(5).repeat(20)
    label = (obs % 2).long()
    fit_bc(learner, _rows(obs, label), BCConfig(num_steps=200))
    assert torch.equal(_greedy(learner, torch.arange(5)), torch.tensor([0, 1, 0, 1, 0]))
    assert learner.normalizer is None  # nothing to normalise on integer states


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (Bounded(-1.0, 1.0, shape=(4, 2)), "shape \\[action_dim\\]"),
        (Categorical(3, shape=(2,)), "scalar action"),
        ("three", "number of actions or a Categorical"),
        (0, "at least one action"),
    ],
)
def test_action_specs_that_do_not_fit_are_refused_by_name(bad, match):
    with pytest.raises(ValueError, match=match):
        ActorCritic.mlp(4, bad)  # the class's own check of the action spec


def test_heads_that_do_not_fit_the_action_are_refused_naming_the_valid_ones():
    with pytest.raises(ValueError, match="'deterministic' or 'normal' or 'tanh_normal'"):
        ActorCritic.mlp(4, Bounded(-1.0, 1.0, shape=(1,)), head="categorical")
    with pytest.raises(ValueError, match="needs a bounded action spec"):
        ActorCritic.mlp(4, Unbounded(shape=(1,)), head="tanh_normal")
    assert action_space(Bounded(-1.0, 1.0, shape=(1,))).kind == "continuous"
    assert ActorCritic.mlp(4, Bounded(-1.0, 1.0, shape=(1,))).head == "deterministic"


# ------------------------------------------------------------------ normaliser
def test_the_normaliser_is_fitted_once_from_the_first_fit_and_is_then_frozen():
    obs = torch.randn(200, 3, generator=G) * torch.tensor([100.0, 1.0, 0.001]) + 7.0
    rows = _rows(obs, torch.zeros(200, dtype=torch.long))
    learner = build("for_env", TaskSpec.from_specs(3, 2), seed=0)
    assert not learner.normalizer.is_fitted
    fit_bc(learner, rows, BCConfig(num_steps=1))
    assert torch.allclose(learner.normalizer.loc, obs.double().mean(0).float())
    assert torch.allclose(learner.normalizer.scale, obs.double().std(0, correction=0).float())
    loc = learner.normalizer.loc.clone()
    fit_bc(learner, _rows(obs + 1000.0, rows.get(keys.EXPERT_ACTION)), BCConfig(num_steps=1))
    assert torch.equal(learner.normalizer.loc, loc)  # the weights were trained with these


def test_the_normaliser_is_saved_with_the_learner(tmp_path):
    obs = torch.randn(64, 3, generator=G) * 10.0 + 3.0
    rows = _rows(obs, (obs[:, 0] > 3.0).long())
    rows.set(keys.ACTION, rows.get(keys.EXPERT_ACTION))
    buffer = DemonstrationBuffer()
    buffer.extend(_with_episode_keys(rows))
    learner = build("for_env", TaskSpec.from_specs(3, 2), seed=0)
    fit_bc(learner, buffer, BCConfig(num_steps=5))
    buffer.save(tmp_path / "ckpt", learner=learner)
    fresh = build("for_env", TaskSpec.from_specs(3, 2), seed=1)
    DemonstrationBuffer.load(tmp_path / "ckpt", learner=fresh)
    assert fresh.normalizer.is_fitted
    assert torch.equal(fresh.normalizer.loc, learner.normalizer.loc)
    assert torch.equal(_greedy(fresh, obs), _greedy(learner, obs))


def _with_episode_keys(rows: TensorDict) -> TensorDict:
    n = rows.shape[0]
    rows.set(keys.EXPERT_EXECUTED, torch.ones(n, dtype=torch.bool))
    rows.set(keys.EPISODE, torch.zeros(n, dtype=torch.long))
    rows.set(keys.ROUND, torch.zeros(n, dtype=torch.long))
    rows.set(keys.STEP, torch.arange(n))
    done = torch.zeros(n, 1, dtype=torch.bool)
    done[-1] = True
    nxt = {keys.REWARD: torch.zeros(n, 1), keys.DONE: done, keys.TERMINATED: done.clone()}
    nxt[keys.TRUNCATED] = torch.zeros(n, 1, dtype=torch.bool)
    rows.set(keys.NEXT, TensorDict(nxt, [n]))
    return rows


def test_the_policy_never_writes_normalised_observations_into_the_tensordict():
    obs = torch.randn(32, 3, generator=G) * 50.0
    learner = build("for_env", TaskSpec.from_specs(3, 2), seed=0)
    fit_bc(learner, _rows(obs, torch.zeros(32, dtype=torch.long)), BCConfig(num_steps=1))
    td = TensorDict({keys.OBSERVATION: obs.clone()}, [32])
    out = learner.policy(td)
    assert torch.equal(out.get(keys.OBSERVATION), obs)  # what an expert reads after it
    assert set(out.keys()) <= {keys.OBSERVATION, keys.ACTION, keys.LOGITS}


def test_fit_bc_refuses_non_finite_observations_naming_them():
    obs = torch.randn(8, 3, generator=G)
    obs[3, 1] = float("inf")
    with pytest.raises(ValueError, match="NaN or inf"):
        fit_bc(
            build("for_env", TaskSpec.from_specs(3, 2)),
            _rows(obs, torch.zeros(8, dtype=torch.long)),
        )
    with pytest.raises(ValueError, match="NaN or inf"):
        build("for_env", TaskSpec.from_specs(3, 2)).act(obs)


# ------------------------------------------------------------ learner vs env
def test_a_learner_that_does_not_fit_the_env_is_refused_naming_both():
    from imitrl.envs import make_env

    cartpole, pendulum = make_env("CartPole-v1", seed=0), make_env("Pendulum-v1", seed=0)
    build("for_env", cartpole).check_env(cartpole)
    build("for_env", pendulum).check_env(pendulum)
    cases = [
        (
            build("for_env", TaskSpec.from_specs(4, 3)),
            cartpole,
            "writes 3 discrete actions; the env takes 2",
        ),
        (
            build("for_env", TaskSpec.from_specs(5, 2)),
            cartpole,
            r"shape \(5,\); the env gives shape \(4,\)",
        ),
        (build("for_env", cartpole), pendulum, r"shape \(4,\); the env gives shape \(3,\)"),
        (
            ActorCritic.mlp(3, Bounded(-1.0, 1.0, shape=(1,))),
            pendulum,
            r"in \[\[-1.0\], \[1.0\]\]; the env takes continuous actions of size 1 in \[\[-2.0\]",
        ),
        (
            build("cross_entropy", TaskSpec(action=4, num_states=15)),
            _lake_env(),
            "15 states; the env gives 16 states",
        ),
    ]
    for learner, env, match in cases:
        with pytest.raises(ValueError, match=match):
            learner.check_env(env)


def _lake_env():
    from imitrl.envs import TabularEnv
    from imitrl.tabular import TabularMDP

    return TabularEnv(TabularMDP.from_gym("FrozenLake-v1", gamma=0.95), batch_size=(2,), seed=0)


def test_evaluate_refuses_a_learner_that_does_not_fit_the_env_before_any_step():
    from imitrl.envs import make_env
    from imitrl.evaluation import evaluate

    env = make_env("CartPole-v1", seed=0)
    with pytest.raises(ValueError, match=r"shape \(5,\); the env gives shape \(4,\)"):
        evaluate(env, build("for_env", TaskSpec.from_specs(5, 2)), 1)
    with pytest.raises(ValueError, match="writes 3 discrete actions; the env takes 2"):
        evaluate(env, build("for_env", TaskSpec.from_specs(4, 3)), 1)


def test_rows_alone_describe_their_task():
    """``TaskSpec.from_rows``: a dataset with no env (``imitrl bc --env none``)."""
    from tensordict import TensorDict
    from torchrl.data import Bounded

    n = 6
    labels = torch.tensor([[0.0, 0.5], [-1.0, 0.5], [2.0, 0.5]]).repeat(2, 1)
    rows = TensorDict(
        {"observation": torch.randn(n, 3), "expert_action": labels,
         "pixels": torch.zeros(n, 8, 8, 3, dtype=torch.uint8)}, [n],
    )  # fmt: skip
    task = TaskSpec.from_rows(rows)
    assert task.observation_dim == 3 and task.pixels == ((8, 8, 3), "pixels")
    assert isinstance(task.action, Bounded)
    # the second dimension never varied: a sliver of range around 0.5
    low, high = task.action.space.low, task.action.space.high
    assert torch.equal(low, torch.tensor([-1.0, 0.5 - 1e-3])), low
    assert torch.equal(high, torch.tensor([2.0, 0.5 + 1e-3])), high

    states = TensorDict({"observation": torch.tensor([0, 3, 5]),
                         "expert_action": torch.tensor([1, 0, 2])}, [3])  # fmt: skip
    task = TaskSpec.from_rows(states)
    assert (task.num_states, task.action) == (6, 3)
    assert TaskSpec.from_rows(states, action=4).action == 4  # a recorded space wins

    # a DAgger dataset: the learner executed actions beyond the expert's labels (a hostile
    # review: its own executed actions were then refused as outside the task's bounds)
    acted = rows.clone()
    acted["action"] = labels.clone()
    acted["action"][0, 0] = 3.5
    wide = TaskSpec.from_rows(acted).action
    assert wide.space.low[0].item() == -1.0 and wide.space.high[0].item() == 3.5
    states["action"] = torch.tensor([1, 4, 2])
    assert TaskSpec.from_rows(states).action == 5

    with pytest.raises(ValueError, match="rows need 'expert_action'"):
        TaskSpec.from_rows(TensorDict({"observation": torch.zeros(2, 3)}, [2]))
    odd = TensorDict({"observation": torch.zeros(2, 3, 4), "expert_action": labels[:2]}, [2])
    with pytest.raises(ValueError, match=r"expected float32 \[N, d\]"):
        TaskSpec.from_rows(odd)


@pytest.mark.parametrize(
    ("key", "values", "what"),
    [
        ("expert_action", [0, 10**11], "'expert_action' \\(integer actions\\) range over \\[0, 100000000000\\]"),
        ("expert_action", [-1, 2], "'expert_action' \\(integer actions\\) range over \\[-1, 2\\]"),
        ("observation", [0, 1 << 16], "'observation' \\(integer states\\) range over \\[0, 65536\\]"),
        ("observation", [-5, 3], "'observation' \\(integer states\\) range over \\[-5, 3\\]"),
    ],
)  # fmt: skip
def test_rows_whose_largest_integer_would_size_the_network_are_refused(key, values, what):
    """A hostile review: one action of 10^11 in a 60 KB dataset asked ``imitrl bc --env
    none`` for a 25 TB output layer."""
    from tensordict import TensorDict

    from imitrl.limits import MAX_CATEGORIES

    rows = {"observation": torch.tensor([0, 1]), "expert_action": torch.tensor([1, 0])}
    rows[key] = torch.tensor(values)
    with pytest.raises(ValueError, match=what + rf": expected integers in \[0, {MAX_CATEGORIES}\)"):
        TaskSpec.from_rows(TensorDict(rows, [2]))
    rows[key] = torch.tensor([0, MAX_CATEGORIES - 1])  # the largest allowed builds
    task = TaskSpec.from_rows(TensorDict(rows, [2]))
    assert MAX_CATEGORIES in (task.num_states, task.action)


def test_float64_observations_are_refused_naming_the_cast():
    """A hostile review: a GymWrapper of a float64 env built a learner that failed in its
    first matmul ("Double and Float")."""
    action = Bounded(-1.0, 1.0, (1,))
    with pytest.raises(ValueError, match=r"torch\.float64; imitrl's learners compute in float32"):
        TaskSpec.from_specs(Unbounded((3,), dtype=torch.float64), action)
    assert TaskSpec.from_specs(Unbounded((3,)), action).observation_dim == 3

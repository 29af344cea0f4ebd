"""ActorCritic, experts and the beta mixture: contracts, shapes, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.learners import TaskSpec, build
from imitrl.policies import BetaMixer, Expert, behaviour_policy


def test_tabular_starts_exactly_uniform_with_zero_values():
    ac = build("cross_entropy", TaskSpec(action=4, num_states=16), value=True)
    p = ac.probs(torch.arange(16))
    assert torch.equal(p, torch.full((16, 4), 0.25))
    assert torch.equal(ac.values(torch.arange(16)), torch.zeros(16))
    assert ac.greedy_table().tolist() == [0] * 16  # four-way ties go to action 0


def test_array_boundary_types():
    ac = build("cross_entropy", TaskSpec(action=4, num_states=16), value=True)
    assert isinstance(ac.act_greedy(3), int)
    assert isinstance(ac.act_greedy(np.int64(3)), int)
    out = ac.act_greedy(np.array([1, 2]))
    assert isinstance(out, np.ndarray) and out.dtype == np.int64
    assert isinstance(ac.act_greedy(torch.tensor([1, 2])), torch.Tensor)
    assert isinstance(ac.values(5), float)
    lp = ac.log_prob(np.repeat(9, 4), np.arange(4))
    assert isinstance(lp, np.ndarray) and np.allclose(np.exp(lp), 0.25)
    lp_t = ac.log_prob(torch.tensor([1]), torch.tensor([2]))
    assert lp_t.requires_grad  # tensors in: the graph is kept for training


def test_log_prob_is_log_softmax_of_the_table():
    ac = build("cross_entropy", TaskSpec(action=3, num_states=5))
    with torch.no_grad():
        ac.policy.module[0].module.weight.copy_(
            torch.randn(5, 3, generator=torch.Generator().manual_seed(0))
        )
    s, a = torch.tensor([0, 1, 4, 4]), torch.tensor([2, 0, 1, 2])
    ref = torch.log_softmax(ac.policy.module[0].module.weight, -1)[s, a]
    assert torch.allclose(ac.log_prob(s, a), ref)


def test_greedy_is_argmax_of_logits_with_lowest_ties():
    ac = build("cross_entropy", TaskSpec(action=4, num_states=3))
    with torch.no_grad():
        ac.policy.module[0].module.weight.copy_(
            torch.tensor([[0.0, 2.0, 2.0, 1.0], [5.0, 5.0, 5.0, 5.0], [-1.0, -1.0, 0.0, -3.0]])
        )
    assert ac.greedy_table().tolist() == [1, 0, 2]


def test_sampling_reproducible_with_a_generator_and_matches_probs():
    ac = build("cross_entropy", TaskSpec(action=3, num_states=2))
    with torch.no_grad():
        ac.policy.module[0].module.weight.copy_(
            torch.log(torch.tensor([[0.2, 0.3, 0.5], [1.0, 1.0, 1.0]]))
        )
    a1 = ac.act(np.zeros(20000, dtype=np.int64), torch.Generator().manual_seed(1))
    a2 = ac.act(np.zeros(20000, dtype=np.int64), torch.Generator().manual_seed(1))
    assert np.array_equal(a1, a2)
    freq = np.bincount(a1, minlength=3) / a1.size
    assert np.allclose(freq, [0.2, 0.3, 0.5], atol=0.02)


@pytest.mark.parametrize(
    ("obs", "match"),
    [
        (16, r"outside \[0, 16\)"),
        (-1, r"outside \[0, 16\)"),
        (np.array([0.5]), "integer state observations"),
        ("3", "tensor, numpy array or number"),
    ],
)
def test_tabular_bad_observations(obs, match):
    ac = build("cross_entropy", TaskSpec(action=4, num_states=16))
    with pytest.raises(ValueError, match=match):
        ac.act_greedy(obs)


def test_mlp_bad_observations():
    ac = build("for_env", TaskSpec.from_specs(4, 2))
    with pytest.raises(ValueError, match="NaN"):
        ac.act_greedy(np.array([[0.0, np.nan, 0.0, 0.0]], dtype=np.float32))
    with pytest.raises(ValueError, match="trailing shape"):
        ac.act_greedy(np.zeros((2, 3), dtype=np.float32))


def test_mlp_heads_respect_bounds_and_seed():
    spec = Bounded(-2.0, 3.0, shape=(2,))
    x = np.random.default_rng(0).normal(size=(256, 5)).astype(np.float32) * 10
    for head in ("tanh_normal", "deterministic"):
        ac = build("for_env", TaskSpec.from_specs(5, spec), head=head, hidden=(16,))
        for a in (ac.act(x, torch.Generator().manual_seed(0)), ac.act_greedy(x)):
            assert a.shape == (256, 2) and (a >= -2.0).all() and (a <= 3.0).all()
        twin = build("for_env", TaskSpec.from_specs(5, spec), head=head, hidden=(16,))
        assert np.array_equal(ac.act_greedy(x), twin.act_greedy(x))  # init is seeded
    with pytest.raises(ValueError, match="no action distribution"):
        build("for_env", TaskSpec.from_specs(5, spec), head="deterministic").log_prob(
            x, np.zeros((256, 2), np.float32)
        )
    with pytest.raises(ValueError, match="head"):
        build("for_env", TaskSpec.from_specs(5, 3), head="tanh_normal")


def test_expert_writes_only_its_own_key():
    expert = Expert.from_table(torch.tensor([3, 2, 1, 0]))
    td = TensorDict(
        {
            keys.OBSERVATION: torch.tensor([0, 1, 2, 3]),
            keys.ACTION: torch.zeros(4, dtype=torch.long),
        },
        [4],
    )
    out = expert(td)
    assert out[keys.EXPERT_ACTION].tolist() == [3, 2, 1, 0]
    assert out[keys.ACTION].tolist() == [0, 0, 0, 0]  # a learner's key is untouched
    driven = expert.as_actor()(td.clone())
    assert driven[keys.ACTION].tolist() == [3, 2, 1, 0] and driven[keys.EXPERT_EXECUTED].all()


def test_expert_constructors():
    Q = torch.tensor([[0.0, 1.0], [2.0, 2.0]])
    assert Expert.from_q(Q)(TensorDict({keys.OBSERVATION: torch.tensor([0, 1])}, [2]))[
        keys.EXPERT_ACTION
    ].tolist() == [1, 0]
    fn = Expert.from_callable(lambda obs: (obs.sum(-1) > 0).long())
    td = TensorDict({keys.OBSERVATION: torch.tensor([[1.0, 1.0], [-1.0, -2.0]])}, [2])
    assert fn(td)[keys.EXPERT_ACTION].tolist() == [1, 0]
    learner = build("cross_entropy", TaskSpec(action=2, num_states=4))
    wrapped = Expert.from_policy(learner.policy)
    out = wrapped(TensorDict({keys.OBSERVATION: torch.arange(4)}, [4]))
    assert out[keys.EXPERT_ACTION].tolist() == [0, 0, 0, 0] and keys.ACTION not in out.keys()
    with pytest.raises(ValueError, match="1-D integer"):
        Expert.from_table(torch.zeros(3))
    with pytest.raises(ValueError, match=r"outside \[0, 4\)"):
        Expert.from_table(torch.tensor([0, 1, 0, 1]))(
            TensorDict({keys.OBSERVATION: torch.tensor([7])}, [1])
        )


def test_beta_mixer_extremes_and_validation():
    expert = Expert.from_table(torch.ones(8, dtype=torch.long))
    learner = build("cross_entropy", TaskSpec(action=2, num_states=8))  # greedy action 0 everywhere
    td = TensorDict({keys.OBSERVATION: torch.arange(8)}, [8])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for beta, want in ((1.0, 1), (0.0, 0)):
            out = behaviour_policy(expert, learner.policy, BetaMixer(beta))(td.clone())
            assert (out[keys.ACTION] == want).all()
            assert (out[keys.EXPERT_EXECUTED] == (beta == 1.0)).all()
            assert (out[keys.LEARNER_ACTION] == 0).all() and (out[keys.EXPERT_ACTION] == 1).all()
    with pytest.raises(ValueError, match=r"beta must be in \[0, 1\]"):
        BetaMixer(1.5)
    with pytest.raises(ValueError, match="beta must be 1"):
        behaviour_policy(expert, None, BetaMixer(0.5))


@pytest.mark.parametrize("head", ["normal_free", "tanh_normal_free"])
def test_free_heads_keep_one_learned_scale_for_every_state(head):
    """The ``_free`` heads: the scale is a parameter per action dimension (std 1 at the
    start), the same in every state, and a likelihood fit moves it; the state-dependent
    heads read theirs off the network, so it differs between states."""
    from imitrl.algorithms import BCConfig, fit_bc

    spec = Bounded(-2.0, 2.0, shape=(2,))
    obs = torch.randn(64, 3, generator=torch.Generator().manual_seed(0))
    ac = build("for_env", TaskSpec.from_specs(3, spec), head=head, hidden=(16,), seed=0)
    params = ac.policy.module[0](TensorDict({keys.OBSERVATION: obs}, [64]))
    assert torch.equal(params[keys.SCALE], torch.ones(64, 2))
    label = (obs[:, :2] * 0.5).clamp(-1.5, 1.5)
    rows = TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, [64])
    fit_bc(ac, rows, BCConfig(num_steps=200, batch_size=64))
    after = ac.policy.module[0](TensorDict({keys.OBSERVATION: obs}, [64]))[keys.SCALE]
    assert bool((after == after[0]).all()) and bool((after[0] < 0.9).all())  # shrunk
    (free,) = [p for n, p in ac.policy.named_parameters() if "state_independent_scale" in n]
    assert free.shape == (2,) and torch.equal(after[0], free.exp())
    other = build(
        "for_env",
        TaskSpec.from_specs(3, spec),
        head=head.removesuffix("_free"),
        hidden=(16,),
        seed=0,
    )
    varying = other.policy.module[0](TensorDict({keys.OBSERVATION: obs}, [64]))[keys.SCALE]
    assert not bool((varying == varying[0]).all())


def test_a_learner_carries_a_value_head_only_when_asked_for():
    """BC builds none (and no opt_v); GAIL and AIRL ask for one; the policy is the same
    either way, weight for weight (the value's weights are drawn after the policy's)."""
    for task in (TaskSpec(action=4, num_states=16), TaskSpec.from_specs(5, 3)):
        plain, critic = build("default", task, seed=3), build("default", task, seed=3, value=True)
        assert plain.value is None and set(plain.optimizers()) == {"opt_pi"}
        assert critic.value is not None and set(critic.optimizers()) == {"opt_pi", "opt_v"}
        for a, b in zip(plain.policy.parameters(), critic.policy.parameters(), strict=True):
            assert torch.equal(a, b)
        with pytest.raises(ValueError, match="no value head"):
            plain.values(torch.zeros(2, dtype=torch.long) if task.num_states else torch.zeros(2, 5))
    with pytest.raises(ValueError, match="builds no value head"):
        build("flow", TaskSpec.from_specs(5, Bounded(-1.0, 1.0, shape=(2,))), value=True)

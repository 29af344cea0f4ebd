"""Exact tabular AIRL (imitrl.tabular.airl): decomposition, occupancies, identification, transfer."""

from __future__ import annotations

import pytest
import torch

from imitrl.tabular import airl as A
from imitrl.tabular.dp import greedy, policy_evaluation, value_iteration
from imitrl.tabular.finite_horizon import success_probability
from imitrl.tabular.mdp import TabularMDP

GAMMA = 0.95


def _lake(**kwargs) -> TabularMDP:
    return TabularMDP.from_gym("FrozenLake-v1", GAMMA, make_kwargs=kwargs, max_steps=100)


@pytest.fixture(scope="module")
def lake() -> TabularMDP:
    return _lake()


def _truth(mdp: TabularMDP, beta: float) -> torch.Tensor:
    """The env's reward on entering the goal as a reward on the absorbing goal state:
    ``gamma^t`` on entering at ``t`` equals ``c sum_{k > t} gamma^k`` for ``c = (1 - gamma) / gamma``."""
    return beta * (1 - GAMMA) / GAMMA * mdp.goal.double()


def test_shaped_reward_is_g_plus_gamma_expected_h_next_minus_h(lake):
    g = torch.linspace(-1, 1, 16, dtype=torch.float64)
    h = torch.cos(torch.arange(16, dtype=torch.float64))
    f = A.shaped_reward(lake, g, h, GAMMA)
    for s in (0, 6, 14, 15):
        for a in range(4):
            expected = g[s] + GAMMA * sum(lake.P[s, a, t] * h[t] for t in range(16)) - h[s]
            assert float(f[s, a]) == pytest.approx(float(expected), abs=1e-12)


def test_shaping_under_the_planning_kernel_leaves_the_plan_unchanged(lake):
    """Potential shaping is policy-invariant under the kernel it is taken in: the plans
    are worth the same (they may break a tie differently, as on state 6 of the lake)."""
    g = torch.zeros(16, dtype=torch.float64)
    g[lake.goal] = 1.0
    h = torch.randn(16, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for target in (lake, _lake(is_slippery=False)):
        shaped = A.plan(target, A.shaped_reward(target, g, h, GAMMA))
        plain = A.plan(target, g)
        values = [target.initial @ policy_evaluation(target, p) for p in (shaped, plain)]
        assert float(values[0]) == pytest.approx(float(values[1]), abs=1e-12)
        # and shaping under another kernel does change the plan's worth on this one
    other = A.plan(_lake(is_slippery=False), A.shaped_reward(lake, g, 50 * h, GAMMA))
    assert success_probability(_lake(is_slippery=False), other) < 1.0


def test_discounted_occupancy_is_the_normalised_power_series(lake):
    noise = torch.randn(16, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    pi = torch.softmax(noise, -1)
    rho = A.discounted_occupancy(lake, pi)
    p_pi = torch.einsum("sa,sat->st", pi, lake.P)
    d, total = lake.initial.clone(), torch.zeros(16, dtype=torch.float64)
    for t in range(2000):
        total += (1 - GAMMA) * GAMMA**t * d
        d = d @ p_pi
    torch.testing.assert_close(rho, total[:, None] * pi, atol=1e-12, rtol=0)
    assert float(rho.sum()) == pytest.approx(1.0, abs=1e-12)


def test_empirical_occupancy_of_hand_written_episodes(lake):
    # episode 0: 0 -a1-> 4 -a2-> 5 (a hole: terminal); episode 1: cut by the limit at 0
    rows = torch.tensor([[0, 0, 0, 1, 4], [0, 1, 4, 2, 5], [1, 0, 0, 0, 0]])
    rho = A.empirical_occupancy(lake, rows)
    raw = torch.zeros(16, 4, dtype=torch.float64)
    raw[0, 1] += 0.05 / 2
    raw[4, 2] += 0.05 * GAMMA / 2
    raw[5, :] += GAMMA**2 / 2 / 4  # the absorbing tail of episode 0
    raw[0, 0] += 0.05 / 2
    torch.testing.assert_close(rho, raw / raw.sum(), atol=1e-15, rtol=0)


def test_empirical_occupancy_refuses_bad_rows(lake):
    with pytest.raises(ValueError, match=r"\[M, 5\]"):
        A.empirical_occupancy(lake, torch.zeros(3, 4, dtype=torch.long))
    with pytest.raises(ValueError, match="actions must lie in"):
        A.empirical_occupancy(lake, torch.tensor([[0, 0, 0, 7, 1]]))
    with pytest.raises(ValueError, match="live state"):
        A.empirical_occupancy(lake, torch.tensor([[0, 0, 5, 0, 5]]))  # acting in a hole


def test_airl_refuses_an_undiscounted_problem(lake):
    with pytest.raises(ValueError, match=r"discount in \(0, 1\)"):
        A.airl(lake, torch.full((16, 4), 1 / 64, dtype=torch.float64), gamma=1.0)
    with pytest.raises(ValueError, match="inverse temperature"):
        A.boltzmann_policy(lake, 0.0)
    with pytest.raises(ValueError, match="zero everywhere"):
        A.airl(lake, torch.zeros(16, 4, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"\[16, 4\]"):
        A.airl(lake, torch.ones(4, 16, dtype=torch.float64))


def test_the_boltzmann_demonstrator_is_the_game_s_fixed_point(lake):
    """f = log pi_E at (g, h) = (the true reward, the soft value): the discriminator
    cannot tell the demonstrator from itself there."""
    beta = 20.0
    pi = A.boltzmann_policy(lake, beta)
    # the soft value of the state-only reward (the goal absorbing and paying every step)
    truth = _truth(lake, beta)
    q, v = A.soft_bellman(lake, truth[:, None].expand(-1, 4), GAMMA, sweeps=3000)
    live = ~lake.terminal
    torch.testing.assert_close(torch.log(pi)[live], (q - v[:, None])[live], atol=1e-10, rtol=0)
    f = A.shaped_reward(lake, truth, v, GAMMA)
    torch.testing.assert_close(f[live], torch.log(pi)[live], atol=1e-9, rtol=0)


def test_airl_recovers_the_demonstrator_s_reward_up_to_a_constant(lake):
    beta = 20.0
    pi = A.boltzmann_policy(lake, beta)
    fit = A.airl(lake, A.discounted_occupancy(lake, pi))
    diff = fit.g - _truth(lake, beta)
    assert float((diff - diff.mean()).abs().max()) < 0.01  # measured 0.0006; the goal's is 1.05
    assert float(fit.occupancy_gap[-1]) < 1e-4
    assert float(fit.occupancy_gap[-1]) < float(fit.occupancy_gap[0])


def test_the_learned_g_transfers_and_the_source_shaped_f_does_not(lake):
    """Planned against under the non-slippery kernel, AIRL's g does what that kernel's own
    expert does (exact success 1); its f, shaped under the slippery kernel, does not."""
    pi = A.boltzmann_policy(lake, 20.0)
    fit = A.airl(lake, A.discounted_occupancy(lake, pi))
    target = _lake(is_slippery=False)
    own = greedy(target.backup(value_iteration(target, 1000)[-1]))
    assert success_probability(target, own) == pytest.approx(1.0)
    assert success_probability(target, A.plan(target, fit.g)) == pytest.approx(1.0)
    f_source = A.shaped_reward(lake, fit.g, fit.h, GAMMA)
    assert success_probability(target, A.plan(target, f_source)) < 0.5


def test_sampled_episodes_are_a_function_of_the_seed_alone(lake):
    pi = A.boltzmann_policy(lake, 20.0)
    torch.manual_seed(123)
    before = torch.rand(3)
    torch.manual_seed(123)
    a = A.sample_episodes(lake, pi, 50, seed=7)
    assert torch.equal(torch.rand(3), before)  # the global stream is untouched
    assert torch.equal(a, A.sample_episodes(lake, pi, 50, seed=7))
    assert not torch.equal(a, A.sample_episodes(lake, pi, 50, seed=8))
    # every episode starts at t = 0 in the start state and is contiguous in time
    assert set(a[a[:, 1] == 0, 0].tolist()) == set(range(50))
    assert (a[a[:, 1] == 0, 2] == 0).all()
    for ep in (0, 17, 49):
        rows = a[a[:, 0] == ep]
        assert torch.equal(rows[1:, 2], rows[:-1, 4])  # s_{t+1} is the next row's s
        assert not lake.terminal[rows[:-1, 4]].any()


def test_airl_is_deterministic(lake):
    pi = A.boltzmann_policy(lake, 20.0)
    rho = A.empirical_occupancy(lake, A.sample_episodes(lake, pi, 30, seed=3))
    one, two = A.airl(lake, rho, rounds=20), A.airl(lake, rho, rounds=20)
    assert torch.equal(one.g, two.g) and torch.equal(one.h, two.h)


def test_bad_airl_inputs_are_refused_naming_what_was_expected(lake):
    from imitrl.experiments.frozenlake.config import StudyConfig

    with pytest.raises(ValueError, match=r"--airl-beta must be > 0"):
        StudyConfig(airl_beta=0.0)
    with pytest.raises(ValueError, match=r"--airl-rounds must be an integer >= 1"):
        StudyConfig(airl_rounds=0)
    pi = A.boltzmann_policy(lake, 20.0)
    with pytest.raises(ValueError, match="episodes >= 1"):
        A.sample_episodes(lake, pi, 0, seed=0)
    with pytest.raises(ValueError, match=r"finite \[S\] or \[S, A\]"):
        A.plan(lake, torch.zeros(3, dtype=torch.float64))

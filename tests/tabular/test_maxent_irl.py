"""Exact MaxEnt / MCE IRL: brute-force enumeration, finite differences, convergence, errors."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from imitrl.tabular import (
    Demonstrations,
    TabularMDP,
    dual_objective,
    feature_expectations,
    likelihood_gradient,
    linear_reward,
    log_likelihood,
    maxent_irl,
    next_state_features,
    occupancy_measure,
    soft_value_iteration,
    state_action_features,
    state_features,
)

# ---------------------------------------------------------------- tiny MDPs, brute force


def _tiny(stochastic: bool) -> TabularMDP:
    """States 0, 1 live, 2 terminal; 2 actions; horizon 3; start spread over 0 and 1."""
    P = np.zeros((3, 2, 3))
    if stochastic:
        P[0, 0] = [0.6, 0.3, 0.1]
        P[0, 1] = [0.0, 0.5, 0.5]
        P[1, 0] = [0.7, 0.2, 0.1]
        P[1, 1] = [0.1, 0.1, 0.8]
    else:
        P[0, 0, 1] = P[0, 1, 2] = P[1, 0, 0] = P[1, 1, 1] = 1.0
    P[2, :, 2] = 1.0
    return TabularMDP.from_arrays(
        P,
        np.zeros((3, 2)),
        1.0,
        initial=[0.4, 0.6, 0.0],
        terminal=np.array([False, False, True]),
        max_steps=3,
    )


REWARD = torch.tensor([[0.3, -0.7], [1.1, 0.2], [0.0, 0.0]], dtype=torch.float64)


def _trajectories(mdp: TabularMDP, pi: torch.Tensor, T: int):
    """Every (prob, [(t, s, a), ...]) history from the start distribution, by enumeration."""
    out = []

    def grow(prob, s, t, hist):
        if t == T or bool(mdp.terminal[s]):
            out.append((prob, hist))
            return
        for a in range(mdp.num_actions):
            for s2 in range(mdp.num_states):
                p = prob * float(pi[t, s, a]) * float(mdp.P[s, a, s2])
                if p > 0:
                    grow(p, s2, t + 1, [*hist, (t, s, a)])

    for s0 in range(mdp.num_states):
        if mdp.initial[s0] > 0:
            grow(float(mdp.initial[s0]), s0, 0, [])
    return out


def test_soft_values_are_log_partition_functions_on_deterministic_dynamics():
    mdp, T = _tiny(stochastic=False), 3
    soft = soft_value_iteration(mdp, REWARD)
    for s0 in (0, 1):
        paths = {}  # distinct trajectories: action sequences agree after termination
        for actions in itertools.product(range(2), repeat=T):
            s, path, ret = s0, [], 0.0
            for a in actions:
                if mdp.terminal[s]:
                    break
                path.append((s, a))
                ret += float(REWARD[s, a])
                s = int(mdp.P[s, a].argmax())
            paths[tuple(path)] = ret
        Z = sum(math.exp(r) for r in paths.values())
        first = [sum(math.exp(r) for p, r in paths.items() if p[0][1] == a) / Z for a in (0, 1)]
        assert abs(float(soft.v[0, s0]) - math.log(Z)) < 1e-10
        assert np.allclose(soft.policy[0, s0].numpy(), first, atol=1e-10, rtol=0)
    assert (soft.v[:, 2] == 0).all()  # terminal: value 0, not log A


def _brute_soft_value(mdp: TabularMDP, s: int, steps_left: int) -> float:
    """Soft value by recursion over histories: log sum_a exp(r + E V') (independent code)."""
    if steps_left == 0 or mdp.terminal[s]:
        return 0.0
    qs = []
    for a in range(mdp.num_actions):
        ev = sum(
            float(mdp.P[s, a, s2]) * _brute_soft_value(mdp, s2, steps_left - 1)
            for s2 in range(mdp.num_states)
            if mdp.P[s, a, s2] > 0
        )
        qs.append(float(REWARD[s, a]) + ev)
    return math.log(sum(math.exp(q) for q in qs))


def test_soft_value_iteration_is_the_max_causal_entropy_optimum_by_enumeration():
    mdp, T = _tiny(stochastic=True), 3
    soft = soft_value_iteration(mdp, REWARD)
    for t in range(T):
        for s in (0, 1):
            assert abs(float(soft.v[t, s]) - _brute_soft_value(mdp, s, T - t)) < 1e-10

    def objective(pi):  # E[sum_t r(s_t, a_t) - log pi_t(a_t|s_t)] over every trajectory
        total = 0.0
        for prob, hist in _trajectories(mdp, pi, T):
            total += prob * sum(float(REWARD[s, a]) - math.log(pi[t, s, a]) for t, s, a in hist)
        return total

    best = float(mdp.initial @ soft.v[0])
    assert abs(objective(soft.policy) - best) < 1e-10  # Gibbs: the optimum's value is V_0
    worse = soft.policy.clone()
    worse[1, 0] = torch.tensor([0.5, 0.5], dtype=torch.float64)
    assert objective(worse) < best - 1e-4
    # the exact occupancy equals the enumerated visit frequencies
    D = torch.zeros(T, 3, 2, dtype=torch.float64)
    for prob, hist in _trajectories(mdp, soft.policy, T):
        for t, s, a in hist:
            D[t, s, a] += prob
    assert torch.allclose(occupancy_measure(mdp, soft.policy), D, atol=1e-12, rtol=0)


# --------------------------------------------------------------------- gradients by FD


def _sampled_demos(mdp: TabularMDP, episodes: int = 6) -> Demonstrations:
    """Episodes of a fixed behaviour policy, sampled with a seeded generator."""
    g = torch.Generator().manual_seed(0)
    rows = []
    for e in range(episodes):
        s = int(torch.multinomial(mdp.initial, 1, generator=g))
        for t in range(3):
            if mdp.terminal[s]:
                break
            a = int(torch.multinomial(torch.tensor([0.3, 0.7]), 1, generator=g))
            rows.append((e, t, s, a))
            s = int(torch.multinomial(mdp.P[s, a], 1, generator=g))
    return Demonstrations.from_tuples(mdp, torch.tensor(rows))


PHI = torch.tensor(
    [
        [[1.0, 0.5], [-0.3, 0.2], [0.0, 0.0]],
        [[0.0, 1.0], [0.7, -1.0], [0.0, 0.0]],
        [[0.4, 0.4], [1.0, 0.3], [0.0, 0.0]],
    ],
    dtype=torch.float64,
)  # [K=3, S=3, A=2]
THETA = torch.tensor([0.2, -0.5, 0.8], dtype=torch.float64)


def _central_difference(f, theta: torch.Tensor, h: float = 1e-5) -> torch.Tensor:
    grad = torch.empty_like(theta)
    for k in range(len(theta)):
        e = torch.zeros_like(theta)
        e[k] = h
        grad[k] = (f(theta + e) - f(theta - e)) / (2 * h)
    return grad


def test_likelihood_gradient_matches_finite_differences_on_sampled_episodes():
    mdp = _tiny(stochastic=True)
    demos = _sampled_demos(mdp)

    def ll(th):
        return log_likelihood(soft_value_iteration(mdp, linear_reward(th, PHI)), demos)

    soft = soft_value_iteration(mdp, linear_reward(THETA, PHI))
    exact = likelihood_gradient(mdp, soft, demos, PHI)
    fd = _central_difference(ll, THETA)
    assert torch.allclose(exact, fd, rtol=1e-6, atol=1e-9)
    # on sampled episodes the likelihood gradient is NOT the naive feature gap
    start = demos.counts[0].sum(1) / demos.episodes
    gap = feature_expectations(demos.counts, PHI) / demos.episodes - feature_expectations(
        occupancy_measure(mdp, soft.policy, start), PHI
    )
    assert (exact - gap).abs().max() > 1e-3


def test_dual_gradient_is_the_feature_gap_and_equals_the_likelihood_on_occupancies():
    mdp = _tiny(stochastic=True)
    demos = _sampled_demos(mdp)

    def dual(th):
        return dual_objective(soft_value_iteration(mdp, linear_reward(th, PHI)), demos, th, PHI)

    soft = soft_value_iteration(mdp, linear_reward(THETA, PHI))
    start = demos.counts[0].sum(1) / demos.episodes
    gap = feature_expectations(demos.counts, PHI) / demos.episodes - feature_expectations(
        occupancy_measure(mdp, soft.policy, start), PHI
    )
    assert torch.allclose(_central_difference(dual, THETA), gap, rtol=1e-6, atol=1e-9)
    # with an exact occupancy as the demonstration, both objectives and gradients agree
    expert = soft_value_iteration(mdp, linear_reward(torch.tensor([1.0, 0.0, -1.0]), PHI))
    occ = Demonstrations.from_occupancy(occupancy_measure(mdp, expert.policy))
    assert abs(log_likelihood(soft, occ) - dual_objective(soft, occ, THETA, PHI)) < 1e-12
    gap_occ = feature_expectations(occ.counts, PHI) - feature_expectations(
        occupancy_measure(mdp, soft.policy), PHI
    )
    assert torch.allclose(likelihood_gradient(mdp, soft, occ, PHI), gap_occ, atol=1e-12)


# ------------------------------------------------------------------------- convergence


PHI_FIT = torch.tensor(
    [[[1, -1], [0, 0], [0, 0]], [[0, 0], [1, -1], [0, 0]], [[1, 1], [-1, -1], [0, 0]]],
    dtype=torch.float64,
)  # [K=3, S=3, A=2]: action preference in 0, in 1, and state 0 over state 1


@pytest.mark.parametrize("objective", ["likelihood", "dual"])
def test_fit_matches_a_soft_optimal_experts_feature_expectations(objective):
    mdp = _tiny(stochastic=True)
    theta_star = torch.tensor([1.0, -0.5, -1.0], dtype=torch.float64)
    expert = soft_value_iteration(mdp, linear_reward(theta_star, PHI_FIT))
    demos = Demonstrations.from_occupancy(occupancy_measure(mdp, expert.policy))
    res = maxent_irl(mdp, demos, PHI_FIT, steps=800, lr=0.1, objective=objective)
    assert res.feature_gap.abs().max() < 1e-6
    assert torch.allclose(res.theta, theta_star, atol=1e-6)  # these features identify theta
    assert res.log_likelihood[-1] > res.log_likelihood[0]
    assert res.policy.shape == (3, 3, 2) and res.reward.shape == (3, 2)
    again = maxent_irl(mdp, demos, PHI_FIT, steps=800, lr=0.1, objective=objective)
    assert torch.equal(again.theta, res.theta)  # deterministic: same digits


def test_plain_gradient_ascent_climbs_the_likelihood():
    mdp = _tiny(stochastic=True)
    demos = _sampled_demos(mdp)
    res = maxent_irl(mdp, demos, PHI, steps=50, lr=0.5, optimizer="sgd")
    assert (res.log_likelihood[1:] >= res.log_likelihood[:-1] - 1e-12).all()
    assert res.log_likelihood[-1] > res.log_likelihood[0] + 0.1


def test_adam_fit_with_state_action_features_matches_expectations():
    mdp = _tiny(stochastic=True)
    expert = soft_value_iteration(mdp, REWARD)
    demos = Demonstrations.from_occupancy(occupancy_measure(mdp, expert.policy))
    res = maxent_irl(mdp, demos, state_action_features(3, 2), steps=1000, lr=0.1)
    assert res.feature_gap.abs().max() < 1e-6


# ---------------------------------------------------------------- demonstrations, features


def test_buffer_rows_and_tuples_give_the_same_counts():
    mdp = _tiny(stochastic=True)
    tuples = torch.tensor([[0, 0, 0, 1], [0, 1, 1, 0], [4, 0, 1, 1], [4, 1, 1, 1]])
    rows = TensorDict(
        {
            "episode": tuples[:, 0],
            "step": tuples[:, 1],
            "observation": tuples[:, 2],
            "expert_action": tuples[:, 3],
            "action": torch.zeros(4, dtype=torch.long),  # executed action: not the label
        },
        batch_size=[4],
    )
    a = Demonstrations.from_tuples(mdp, tuples)
    b = Demonstrations.from_rows(mdp, rows)
    assert torch.equal(a.counts, b.counts) and a.episodes == b.episodes == 2
    assert a.counts[1, 1].tolist() == [1.0, 1.0]


def test_feature_builders():
    mdp = _tiny(stochastic=True)
    assert state_features(3, 2)[1, 1].tolist() == [1.0, 1.0]
    assert state_features(3, 2)[0, 1].tolist() == [0.0, 0.0]
    assert state_action_features(3, 2)[3, 1, 1] == 1.0 and state_action_features(3, 2).sum() == 6
    assert next_state_features(mdp)[2, 1, 1] == 0.8  # P(2 | 1, 1)


# ------------------------------------------------------------------------------ errors


def test_bad_inputs_raise_value_errors_that_say_what_was_expected():
    mdp = _tiny(stochastic=True)
    demos = _sampled_demos(mdp)
    with pytest.raises(ValueError, match=r"features must have shape \[K, 3, 2\]"):
        maxent_irl(mdp, demos, torch.zeros(3, 3), steps=1)
    with pytest.raises(ValueError, match=r"theta0 must be finite"):
        maxent_irl(mdp, demos, PHI, steps=1, theta0=torch.tensor([0.0, math.nan, 0.0]))
    with pytest.raises(ValueError, match=r"reward must be finite"):
        soft_value_iteration(mdp, torch.full((3, 2), math.inf))
    with pytest.raises(ValueError, match=r"state must be integers in \[0, 3\)"):
        Demonstrations.from_tuples(mdp, torch.tensor([[0, 0, 3, 0]]))
    with pytest.raises(ValueError, match=r"t must be integers in \[0, 3\)"):
        Demonstrations.from_tuples(mdp, torch.tensor([[0, 3, 0, 0]]))
    with pytest.raises(ValueError, match="terminal"):
        Demonstrations.from_tuples(mdp, torch.tensor([[0, 1, 2, 0]]))
    with pytest.raises(ValueError, match=r"integer \[M, 4\]"):
        Demonstrations.from_tuples(mdp, torch.zeros(2, 4))
    with pytest.raises(ValueError, match="lack the keys"):
        Demonstrations.from_rows(mdp, TensorDict({"observation": torch.zeros(2)}, [2]))
    with pytest.raises(ValueError, match=r"demonstration counts must have shape \[5, 3, 2\]"):
        maxent_irl(mdp, demos, PHI, horizon=5, steps=1)
    with pytest.raises(ValueError, match="objective must be one of"):
        maxent_irl(mdp, demos, PHI, steps=1, objective="bayes")

"""Absorbing states (DAC) in adversarial imitation: the rows and keys they add, the features
the discriminators read, the closed-form tail, and the mechanism through TorchRL's GAE:
with a reward that cannot tell expert from policy (``D = 1/2`` everywhere), how an
episode ends changes its return without absorbing states (the living bias) and not with
them; truncation is bootstrapped, termination is not."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.algorithms.adversarial import (
    AdversarialConfig,
    AIRLDiscriminator,
    GAILDiscriminator,
    gail_reward,
)
from imitrl.algorithms.adversarial.absorbing import (
    absorbing_rows,
    absorbing_tail,
    state_features,
    with_absorbing,
)
from imitrl.algorithms.adversarial.generator import PPOGenerator
from imitrl.algorithms.adversarial.keys import (
    ABSORBING,
    ACTION_FEATURES,
    LEARNED_REWARD,
    STATE_FEATURES,
)
from imitrl.algorithms.adversarial.transitions import expert_transitions
from imitrl.learners import ActorCritic, TaskSpec, build
from imitrl.policies.normalization import ObservationNormalizer

NEXT_OBS, NEXT_TERM = (keys.NEXT, keys.OBSERVATION), (keys.NEXT, keys.TERMINATED)
NEXT_ABS = (keys.NEXT, ABSORBING)


def _demo_rows() -> TensorDict:
    """Two demonstration episodes: 0 terminates after 3 rows, 1 is cut after 2 (truncated)."""
    return TensorDict(
        {
            keys.OBSERVATION: torch.arange(1.0, 11.0).reshape(5, 2),
            keys.ACTION: torch.tensor([1, 0, 1, 1, 0]),
            keys.EPISODE: torch.tensor([0, 0, 0, 1, 1]),
            keys.STEP: torch.tensor([0, 1, 2, 0, 1]),
            keys.EXPERT_EXECUTED: torch.ones(5, dtype=torch.bool),
            NEXT_TERM: torch.tensor([[False], [False], [True], [False], [False]]),
            (keys.NEXT, keys.TRUNCATED): torch.tensor([[False], [False], [False], [False], [True]]),
        },
        batch_size=[5],
    )


def _learner() -> ActorCritic:
    return build(
        "for_env", TaskSpec.from_specs(2, 2), hidden=(8,), normalize=False, seed=0, value=True
    )


# ------------------------------------------------------------------- the rows
def test_with_absorbing_adds_one_absorbing_row_per_terminated_episode():
    tr = expert_transitions(_demo_rows())  # 4 rows: the truncated episode's end is dropped
    assert not tr[ABSORBING].any() and not tr[NEXT_ABS].any()
    before = tr.clone()
    out = with_absorbing(tr)
    assert (tr == before).all()  # the caller's transitions are left alone
    assert out.shape == (5,)  # one terminated episode: one absorbing row
    assert out[ABSORBING].squeeze(-1).tolist() == [False, False, False, False, True]
    assert out[NEXT_ABS].squeeze(-1).tolist() == [False, False, True, False, True]
    assert not out[NEXT_TERM].any()  # nothing ends any more: s_abs loops on itself
    torch.testing.assert_close(out[keys.OBSERVATION][:4], tr[keys.OBSERVATION])
    torch.testing.assert_close(out[keys.ACTION][:4], tr[keys.ACTION])
    assert out[keys.OBSERVATION][4].eq(0).all() and out[keys.ACTION][4] == 0  # placeholders
    assert absorbing_rows(out, 3).shape == (3,) and absorbing_rows(out, 0).shape == (0,)


def test_state_features_normalise_states_and_mark_the_absorbing_one():
    norm = ObservationNormalizer((2,))
    norm.fit(torch.tensor([[0.0, 0.0], [2.0, 4.0]]))  # loc (1, 2), scale (1, 2)
    obs = torch.tensor([[3.0, 6.0], [100.0, -100.0]])
    x = state_features(obs, torch.tensor([[False], [True]]), norm)
    torch.testing.assert_close(x, torch.tensor([[2.0, 2.0, 0.0], [0.0, 0.0, 1.0]]))


def test_absorbing_tail_against_hand_computation():
    reward = torch.tensor([[1.0], [2.0], [0.5]])
    terminated = torch.tensor([[False], [True], [False]])
    out = absorbing_tail(reward, terminated, torch.tensor([[0.3]]), gamma=0.9)
    # the terminated step gains sum_{k >= 1} 0.9^k * 0.3 = 0.9 * 0.3 / 0.1 = 2.7
    torch.testing.assert_close(out, torch.tensor([[1.0], [4.7], [0.5]]))
    with pytest.raises(ValueError, match="gamma"):
        absorbing_tail(reward, terminated, torch.tensor(0.3), gamma=1.0)
    with pytest.raises(ValueError, match="gamma < 1"):
        AdversarialConfig(gamma=1.0, absorbing=True)
    AdversarialConfig(gamma=1.0, absorbing=False)  # no absorbing state, no closed form needed


# --------------------------------------------------------- the discriminators
def test_gail_reads_the_absorbing_state_as_its_indicator_and_no_action():
    disc = GAILDiscriminator(_learner(), hidden=(8,), seed=0)
    pairs = disc.pairs(with_absorbing(expert_transitions(_demo_rows())))
    obs = expert_transitions(_demo_rows())[keys.OBSERVATION]
    torch.testing.assert_close(pairs[STATE_FEATURES][:4, :2], obs)  # normalize=False
    assert pairs[STATE_FEATURES][:4, 2].eq(0).all()
    torch.testing.assert_close(pairs[STATE_FEATURES][4], torch.tensor([0.0, 0.0, 1.0]))
    assert pairs[ACTION_FEATURES][:4].sum(-1).eq(1).all()  # one-hot actions
    assert pairs[ACTION_FEATURES][4].eq(0).all()  # the absorbing state's single action


def test_airl_reads_h_of_the_absorbing_state_and_its_action_has_pi_one():
    learner = _learner()
    disc = AIRLDiscriminator(learner, gamma=0.9, hidden=(8,), seed=0)
    plain = expert_transitions(_demo_rows())
    tr = with_absorbing(plain)
    g, h = disc.network.g, disc.network.h
    with torch.no_grad():
        x = torch.cat([plain[keys.OBSERVATION], torch.zeros(4, 1)], -1)
        x_abs = torch.tensor([[0.0, 0.0, 1.0]])
        f = disc.f(tr)
        # terminal row 2: its s' is s_abs, read by h; the absorbing row loops on s_abs
        torch.testing.assert_close(f[2], (g(x[2:3]) + 0.9 * h(x_abs) - h(x[2:3]))[0])
        torch.testing.assert_close(f[4], (g(x_abs) + (0.9 - 1) * h(x_abs))[0])
        torch.testing.assert_close(disc.f(plain)[2], (g(x[2:3]) - h(x[2:3]))[0])  # h(s') zeroed
    log_pi = disc.log_pi(tr)
    assert log_pi[4].item() == 0.0 and bool((log_pi[:4] < 0).all())
    torch.testing.assert_close(disc.reward(tr)[4], f[4])  # f - log pi, log pi = 0


# ----------------------------------------------------- the mechanism, exactly
def _generator(gamma: float, value: float) -> PPOGenerator:
    """PPO's GAE with lambda = 1 (Monte Carlo returns) and a critic ``V(s) = value``."""
    learner = _learner()
    with torch.no_grad():
        for p in learner.value.parameters():
            p.zero_()
        list(learner.value.parameters())[-1].fill_(value)  # the output layer's bias
    return PPOGenerator(learner, gamma=gamma, gae_lambda=1.0, clip_epsilon=0.2,
                        entropy_coeff=0.0, epochs=1, minibatch_size=8,
                        max_grad_norm=0.5)  # fmt: skip


def _episode(reward: torch.Tensor, terminated: bool) -> TensorDict:
    """One episode ``[1, T]`` whose last step terminated (or was truncated)."""
    T = reward.shape[0]
    end = torch.zeros(1, T, 1, dtype=torch.bool)
    end[0, -1] = True
    return TensorDict(
        {
            keys.OBSERVATION: torch.randn(1, T, 2),
            keys.NEXT: {
                keys.OBSERVATION: torch.randn(1, T, 2),
                LEARNED_REWARD: reward.reshape(1, T, 1),
                keys.DONE: end,
                keys.TERMINATED: end if terminated else torch.zeros_like(end),
            },
        },
        batch_size=[1, T],
    )


def _return_at_start(gen: PPOGenerator, episode: TensorDict) -> float:
    gen.gae(episode)
    return float(episode["value_target"][0, 0])


def test_no_living_bias_with_absorbing_states():
    """``D = 1/2`` everywhere (the discriminator's equilibrium): every step, the absorbing
    state's included, earns ``c = -log(1/2)``, so every policy's return should be
    ``c / (1 - gamma)`` however its episodes end. Without absorbing states an episode that
    terminates after 3 steps earns ``c (1 + gamma + gamma^2)`` instead, less than one
    truncated after 3 steps (bootstrapped through the critic) or still going: living pays."""
    gamma, c = 0.9, float(gail_reward(torch.tensor(0.0)))
    assert math.isclose(c, math.log(2), rel_tol=1e-6)
    full = c / (1 - gamma)
    gen = _generator(gamma, value=full)  # the critic already knows the return
    reward = torch.full((3, 1), c)
    terminated = torch.tensor([[False], [False], [True]])
    truncated = _return_at_start(gen, _episode(reward, terminated=False))
    biased = _return_at_start(gen, _episode(reward, terminated=True))
    fixed = absorbing_tail(reward, terminated, torch.tensor(c), gamma)
    unbiased = _return_at_start(gen, _episode(fixed, terminated=True))
    assert math.isclose(truncated, full, rel_tol=1e-5)  # truncation: V(s') bootstrapped
    assert math.isclose(biased, c * (1 + gamma + gamma**2), rel_tol=1e-5)  # V(s') = 0
    assert biased < 0.3 * full
    assert math.isclose(unbiased, full, rel_tol=1e-5)  # termination = the absorbing tail

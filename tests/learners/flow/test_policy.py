"""Flow matching, DDIM sampling and the chunk losses: each trains on a toy problem to a
stated error; padded chunk entries carry no weight."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK, IS_INIT
from imitrl.learners import build, registry
from imitrl.learners.diffusion import DiffusionPolicy
from imitrl.learners.task import TaskSpec

TASK = TaskSpec(action=Bounded(-1.0, 1.0, shape=(1,)), observation_dim=2)
CONFIG = dict(hidden=(64, 64), lr=3e-3, seed=0)
N = 512


def _toy(bimodal: bool = False) -> TensorDict:
    """``s ~ U(-1, 1)^2``; label ``0.5 s_0`` (or, bimodal, ``+-0.5`` at random)."""
    g = torch.Generator().manual_seed(0)
    obs = 2 * torch.rand(N, 2, generator=g) - 1
    if bimodal:
        label = torch.where(torch.rand(N, 1, generator=g) < 0.5, -0.5, 0.5)
    else:
        label = 0.5 * obs[:, :1]
    return TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, batch_size=[N])


def _act(learner, obs: torch.Tensor, exploration=ExplorationType.RANDOM) -> torch.Tensor:
    td = TensorDict(
        {keys.OBSERVATION: obs, IS_INIT: torch.ones(obs.shape[0], 1, dtype=torch.bool)},
        batch_size=[obs.shape[0]],
    )
    with torch.no_grad(), set_exploration_type(exploration):
        return learner.policy(td).get(keys.ACTION)


@pytest.mark.parametrize(("name", "tol"), [("flow", 0.05), ("diffusion_ddim", 0.08)])
def test_few_step_generative_losses_fit_a_linear_expert(name, tol):
    rows = _toy()
    learner = build(name, TASK, shared=CONFIG)
    fit_bc(learner, rows, BCConfig(num_steps=800, batch_size=128))
    obs = rows.get(keys.OBSERVATION)[:200]
    err = (_act(learner, obs) - 0.5 * obs[:, :1]).abs().mean()
    assert err < tol, f"{name}: mean |a - a*| = {err:.3f}"


def test_flow_keeps_both_modes_of_a_bimodal_expert():
    rows = _toy(bimodal=True)
    learner = build("flow", TASK, shared=CONFIG)
    fit_bc(learner, rows, BCConfig(num_steps=800, batch_size=128))
    a = _act(learner, rows.get(keys.OBSERVATION)[:400])[:, 0]
    below, above = ((a + 0.5).abs() < 0.2).float().mean(), ((a - 0.5).abs() < 0.2).float().mean()
    assert below > 0.3 and above > 0.3, (below, above)


def test_ddim_uses_the_actors_schedule_and_is_reproducible():
    policy = DiffusionPolicy(2, TASK.action, num_steps=20, sampler="ddim", sample_steps=4, seed=3)
    assert torch.allclose(policy._alphas_cumprod, policy.actor.module.alphas_cumprod)
    td = TensorDict({keys.OBSERVATION: torch.zeros(5, 2)}, batch_size=[5])
    with set_exploration_type(ExplorationType.RANDOM):
        a = policy(td.clone()).get(keys.ACTION)
        b = DiffusionPolicy(2, TASK.action, num_steps=20, sampler="ddim", sample_steps=4, seed=3)(
            td.clone()
        ).get(keys.ACTION)
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="sample_steps"):
        DiffusionPolicy(2, TASK.action, num_steps=20, sampler="ddim", sample_steps=21)


def _chunk_rows(horizon: int, pad_value: float) -> TensorDict:
    """Chunk labels ``a*_h = 0.5 s_0 - 0.1 h``; the last half of every chunk is padding
    holding ``pad_value`` (a masked loss must not see it)."""
    rows = _toy()
    obs = rows.get(keys.OBSERVATION)
    h = torch.arange(horizon, dtype=torch.float32)
    chunk = (0.5 * obs[:, :1] - 0.1 * h).unsqueeze(-1)  # [N, H, 1]
    pad = (h >= horizon // 2).expand(N, horizon).clone()
    chunk[pad] = pad_value
    rows.set(EXPERT_CHUNK, chunk)
    rows.set(CHUNK_PAD, pad)
    return rows


@pytest.mark.parametrize(("name", "tol"), [("mse_chunk", 0.05), ("flow_chunk", 0.08)])
def test_chunk_losses_fit_the_unpadded_entries_and_ignore_the_padding(name, tol):
    horizon = registry.get(name).horizon
    learner = build(name, TASK, shared=CONFIG)
    rows = _chunk_rows(horizon, 0.9)
    if name == "mse_chunk":  # the padding's values do not move the loss
        # (flow: padded entries still enter x_t, as the label given there; only their
        # error carries no weight)
        other = build(name, TASK, shared=CONFIG).loss.objective(_chunk_rows(horizon, -0.9))
        assert learner.loss.objective(rows).item() == other.item()
    fit_bc(learner, rows, BCConfig(num_steps=800, batch_size=128))
    obs = rows.get(keys.OBSERVATION)[:200]
    chunk = (
        learner.policy.predict(TensorDict({keys.OBSERVATION: obs}, batch_size=[200]))
        if name == "mse_chunk"
        else _predict_sampled(learner, obs)
    )
    live = rows.get(EXPERT_CHUNK)[:200, : horizon // 2]
    err = (chunk[:, : horizon // 2] - live).abs().mean()
    assert err < tol, f"{name}: mean |chunk - a*| over unpadded entries = {err:.3f}"


def _predict_sampled(learner, obs: torch.Tensor) -> torch.Tensor:
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return learner.policy.predict(TensorDict({keys.OBSERVATION: obs}, batch_size=[200]))


def test_a_flow_policy_samples_from_the_noise_it_is_given():
    learner = build("flow", TASK, shared=CONFIG)
    fit_bc(learner, _toy(bimodal=True), BCConfig(num_steps=200, batch_size=128))
    policy = learner.policy
    obs = torch.rand(6, 2)
    noise = torch.randn(6, 1, generator=torch.Generator().manual_seed(3))
    td = TensorDict({keys.OBSERVATION: obs, keys.POLICY_NOISE: noise}, batch_size=[6])
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        a = policy(td.clone()).get(keys.ACTION)
        b = policy(td.clone()).get(keys.ACTION)
        x = policy.sample(obs, noise).clamp(-1, 1)
        fresh = policy(TensorDict({keys.OBSERVATION: obs}, batch_size=[6])).get(keys.ACTION)
    assert torch.equal(a, b)  # the same noise, the same actions
    assert torch.equal(a, policy.low + (policy.high - policy.low) * (x + 1) / 2)
    assert not torch.equal(a, fresh)  # without it the policy draws its own
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy = policy(td.clone()).get(keys.ACTION)  # greedy starts from 0, noise or not
        zero = policy(TensorDict({keys.OBSERVATION: obs}, batch_size=[6])).get(keys.ACTION)
    assert torch.equal(greedy, zero)
    bad = TensorDict({keys.OBSERVATION: obs, keys.POLICY_NOISE: noise[:, :0]}, batch_size=[6])
    with (
        pytest.raises(ValueError, match="policy_noise"),
        set_exploration_type(ExplorationType.RANDOM),
    ):
        policy(bad)

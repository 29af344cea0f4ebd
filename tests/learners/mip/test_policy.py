"""The minimal iterative policy (issue 47): its loss is the reference's ``mip_loss`` (per
action entry), it acts by two calls of one network with no noise, it learns a toy map,
and padded chunk entries carry no weight."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK
from imitrl.learners import build
from imitrl.learners.mip import MIPLoss, MIPPolicy
from imitrl.learners.mip.policy import T_STAR
from imitrl.learners.task import TaskSpec

SPEC = Bounded(-2.0, 2.0, shape=(3,))


def _rows(n: int = 16, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, 4, generator=g)
    return TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: 4 * torch.rand(n, 3, generator=g) - 2},
                      batch_size=[n])  # fmt: skip


def test_the_loss_is_the_reference_mip_loss_per_action_entry():
    policy = MIPPolicy(4, SPEC, hidden=(8,), normalize=False, seed=0)
    loss = MIPLoss(policy, seed=3)
    rows = _rows()
    got = loss(rows).get("loss_mip")
    # by hand, with the loss's own draws: eps from a generator seeded alike
    eps = torch.randn(16, 3, generator=torch.Generator().manual_seed(3))
    a = (rows.get(keys.EXPERT_ACTION) + 2) / 4 * 2 - 1
    obs = rows.get(keys.OBSERVATION)
    f = policy.net
    first = f(torch.zeros(16, 3), obs, torch.zeros(16, 1))
    second = f(a + (1 - T_STAR) * eps, obs, torch.full((16, 1), T_STAR))
    ref = (
        ((first - a) ** 2).sum(-1) / T_STAR**2 + ((second - a) ** 2).sum(-1) / (1 - T_STAR) ** 2
    ).mean()
    assert torch.allclose(got, ref / 3, rtol=1e-6)  # the reference's, divided by d = 3


def test_acting_is_two_calls_of_one_network_without_noise():
    policy = MIPPolicy(4, SPEC, hidden=(8,), normalize=False, seed=1)
    obs = torch.randn(5, 4)
    first = policy.net(torch.zeros(5, 3), obs, torch.zeros(5, 1))
    x = policy.net(first, obs, torch.full((5, 1), T_STAR)).clamp(-1, 1)
    want = -2 + 4 * (x + 1) / 2
    out = policy(TensorDict({keys.OBSERVATION: obs}, batch_size=[5])).get(keys.ACTION)
    again = policy(TensorDict({keys.OBSERVATION: obs}, batch_size=[5])).get(keys.ACTION)
    assert torch.allclose(out, want) and torch.equal(out, again)


def test_mip_learns_a_toy_map():
    task = TaskSpec(action=Bounded(-1.0, 1.0, shape=(1,)), observation_dim=2)
    g = torch.Generator().manual_seed(0)
    obs = 2 * torch.rand(512, 2, generator=g) - 1
    rows = TensorDict(
        {keys.OBSERVATION: obs, keys.EXPERT_ACTION: 0.5 * obs[:, :1]}, batch_size=[512]
    )
    learner = build("mip", task, shared=dict(hidden=(64, 64), lr=3e-3, seed=0))
    fit_bc(learner, rows, BCConfig(num_steps=1500, batch_size=128, seed=0))
    out = learner.policy(TensorDict({keys.OBSERVATION: obs}, batch_size=[512])).get(keys.ACTION)
    assert float(((out - 0.5 * obs[:, :1]) ** 2).mean()) < 2e-3


def test_padded_chunk_entries_carry_no_weight():
    from imitrl.envs import make_env

    learner = build("mip_chunk", make_env("Pendulum-v1", seed=0), hidden=(8,), seed=0)
    h = learner.horizon
    rows = TensorDict({keys.OBSERVATION: torch.randn(6, 3),
                       EXPERT_CHUNK: torch.zeros(6, h, 1), CHUNK_PAD: torch.zeros(6, h, dtype=torch.bool)},
                      batch_size=[6])  # fmt: skip
    rows.get(CHUNK_PAD)[:, h // 2 :] = True
    policy = learner.policy.network  # the chunked policy's MIP network
    got = MIPLoss(policy, chunked=True, seed=0)(rows).get("loss_mip")
    # by hand: each entry's error, the padded ones weighted 0 (they still enter the
    # second step's input, as the label holds them)
    a = policy.normalize(rows.get(EXPERT_CHUNK).reshape(6, h))
    eps = torch.randn(6, h, generator=torch.Generator().manual_seed(0))
    obs = rows.get(keys.OBSERVATION)
    first = policy.step(torch.zeros_like(a), obs, 0.0)
    second = policy.step(a + (1 - T_STAR) * eps, obs, T_STAR)
    err = (first - a) ** 2 / T_STAR**2 + (second - a) ** 2 / (1 - T_STAR) ** 2
    keep = (~rows.get(CHUNK_PAD)).float()
    assert torch.allclose(got, (err * keep).sum() / keep.sum(), rtol=1e-6)
    assert not torch.allclose(got, err.mean())

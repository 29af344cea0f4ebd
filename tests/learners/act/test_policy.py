"""The ``act`` registry entry: TorchRL's ACTModel / ACTLoss behind imitrl's contracts."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK, IS_INIT
from imitrl.learners import build
from imitrl.learners.act import ACTChunkLoss, ACTPolicy
from imitrl.learners.chunks import CHUNK_HORIZON
from imitrl.learners.task import TaskSpec
from imitrl.policies.chunking import ChunkedPolicy

H = CHUNK_HORIZON
TASK = TaskSpec(action=Bounded(-2.0, 2.0, shape=(1,)), observation_dim=2)


def _toy(n: int = 256, seed: int = 0) -> TensorDict:
    """Chunks ``a_h = tanh(s_0 + 0.1 h)`` (inside the bounds [-2, 2]) of observations ``s``."""
    g = torch.Generator().manual_seed(seed)
    s = torch.rand(n, 2, generator=g) * 2 - 1
    chunk = torch.tanh(s[:, :1] + 0.1 * torch.arange(H)).unsqueeze(-1)  # [n, H, 1]
    return TensorDict(
        {
            keys.OBSERVATION: s,
            keys.EXPERT_ACTION: chunk[:, 0],
            EXPERT_CHUNK: chunk,
            CHUNK_PAD: torch.zeros(n, H, dtype=torch.bool),
        },
        [n],
    )


def test_act_learns_a_toy_chunk_map_to_a_stated_error():
    rows = _toy()
    learner = build("act", TASK, shared=dict(lr=2e-3, seed=0))
    assert isinstance(learner.policy, ChunkedPolicy) and learner.policy.execution.ensemble
    fit_bc(learner, rows, BCConfig(num_steps=120, batch_size=64, seed=0))
    pred = learner.policy.predict(rows.select(keys.OBSERVATION))  # [n, H, 1], z = 0
    label = rows[EXPERT_CHUNK]
    # the labels' spread: predicting their mean chunk errs by about 0.45
    baseline = (label - label.mean(0)).abs().mean()
    assert baseline > 0.3
    assert (pred - label).abs().mean() < 0.06
    # the executed action (temporal ensembling; one query after a reset: the chunk's first)
    td = rows.select(keys.OBSERVATION).set(IS_INIT, torch.ones(len(rows), 1, dtype=torch.bool))
    action = learner.policy(td).get(keys.ACTION)
    assert torch.allclose(action, pred[:, 0])


def test_act_loss_contract_and_reproducibility():
    rows = _toy(32)
    out = []
    for _ in range(2):
        policy = ACTPolicy(2, TASK.action, horizon=H, seed=3)
        loss = ACTChunkLoss(policy, seed=5)
        policy.normalizer.fit(rows[keys.OBSERVATION])
        td = loss(rows)
        assert set(td.keys()) == {"loss_act", "l1", "kl"}
        assert not td["l1"].requires_grad and td["loss_act"].requires_grad
        assert torch.allclose(td["loss_act"], td["l1"] + 10.0 * td["kl"])
        out.append(td["loss_act"].detach())
    assert torch.equal(out[0], out[1])  # same seeds, same latent draws
    with pytest.raises(ValueError, match="ACT labels"):
        loss(rows.set(EXPERT_CHUNK, torch.zeros(32, H + 1, 1)))
    with pytest.raises(ValueError, match="ACTPolicy"):
        ACTChunkLoss(torch.nn.Linear(1, 1))

"""ExpertGate (issue 48): the expert takes over where the rule fires, per lane; the
learner's proposal and the intervention are recorded."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.policies.gate import ActionDistance, ExpertGate


def _td(expert, learner):
    return TensorDict(
        {keys.EXPERT_ACTION: expert, keys.ACTION: learner}, batch_size=[expert.shape[0]]
    )


def test_the_expert_takes_over_where_the_learner_is_farther_than_the_threshold():
    expert = torch.tensor([[0.0, 0.0], [1.0, 1.0], [0.5, -0.5]])
    learner = torch.tensor([[0.3, 0.4], [1.0, 1.1], [0.5, -0.5]])  # distances 0.5, 0.1, 0
    out = ExpertGate(0.2)(_td(expert, learner))
    assert out.get(keys.EXPERT_EXECUTED).tolist() == [True, False, False]
    assert torch.equal(out.get(keys.ACTION), torch.stack([expert[0], learner[1], learner[2]]))
    assert torch.equal(out.get(keys.LEARNER_ACTION), learner)


def test_a_nan_or_inf_proposal_is_taken_over():
    """NaN > threshold is False: a NaN learner action was executed, no intervention kept."""
    expert = torch.tensor([[0.1], [0.1], [0.1]])
    learner = torch.tensor([[float("nan")], [float("inf")], [0.15]])
    out = ExpertGate(0.5)(_td(expert, learner))
    assert out.get(keys.EXPERT_EXECUTED).tolist() == [True, True, False]
    assert out.get(keys.ACTION).flatten().tolist() == pytest.approx([0.1, 0.1, 0.15])


def test_discrete_actions_intervene_where_they_differ_and_a_rule_is_a_parameter():
    out = ExpertGate(0.0)(_td(torch.tensor([0, 1, 2]), torch.tensor([0, 2, 2])))
    assert out.get(keys.EXPERT_EXECUTED).tolist() == [False, True, False]
    assert out.get(keys.ACTION).tolist() == [0, 1, 2]

    def always(expert, learner, batch):
        return torch.ones(batch, dtype=torch.bool)

    out = ExpertGate(always)(_td(torch.zeros(2, 1), torch.ones(2, 1)))
    assert out.get(keys.EXPERT_EXECUTED).all() and (out.get(keys.ACTION) == 0).all()


def test_bad_gates_are_refused():
    with pytest.raises(ValueError, match="threshold must be >= 0"):
        ActionDistance(-1.0)
    with pytest.raises(ValueError, match="put the learner before the gate"):
        ExpertGate(0.1)(TensorDict({keys.EXPERT_ACTION: torch.zeros(2, 1)}, batch_size=[2]))

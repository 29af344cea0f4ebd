"""DAgger with a gated expert and HG-DAgger (issue 48): the gate decides who acts; all
visited states, or only the expert's interventions, are labelled."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, dagger
from imitrl.algorithms.dagger import EnvSource
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.experts import pendulum_expert
from imitrl.learners import build
from imitrl.policies.gate import ExpertGate
from imitrl.runtime import rollout_episodes


def _run(gate, label: str):
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=50)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, pendulum_expert(), 1))
    config = DAggerConfig(rounds=3, episodes_per_round=2, gate=gate, label=label,
                          bc=BCConfig(num_steps=20, batch_size=32))  # fmt: skip
    result = dagger(EnvSource(env, exploration=ExplorationType.DETERMINISTIC), pendulum_expert(),
                    lambda: build("mse", env, hidden=(16,), seed=0), buffer, config)  # fmt: skip
    return result, buffer.data


def test_a_gated_expert_acts_where_the_gate_fires_and_every_state_is_labelled():
    result, rows = _run(ExpertGate(0.5), "all")
    relabelled = rows[rows.get(keys.ROUND) > 0]
    executed = relabelled.get(keys.EXPERT_EXECUTED)
    assert relabelled.shape[0] == 2 * 2 * 50  # every visited state of 2 rounds x 2 episodes
    assert 0 < int(executed.sum()) < executed.numel()
    act, exp = relabelled.get(keys.ACTION), relabelled.get(keys.EXPERT_ACTION)
    assert torch.equal(act[executed], exp[executed])  # the expert drove there
    assert bool(((act - exp).norm(dim=-1)[~executed] <= 0.5).all())  # the learner, close enough
    assert [r.interventions for r in result.rounds[:-1]] == [
        int(executed[relabelled.get(keys.ROUND) == k].sum()) for k in (1, 2)
    ]


def test_hg_dagger_labels_the_interventions_alone():
    result, rows = _run(ExpertGate(0.5), "interventions")
    relabelled = rows[rows.get(keys.ROUND) > 0]
    assert relabelled.get(keys.EXPERT_EXECUTED).all()
    for record in result.rounds[:-1]:
        assert record.rows_collected == record.interventions
    assert relabelled.shape[0] == sum(r.rows_collected for r in result.rounds[:-1]) > 0
    assert result.rounds[-1].rows_trained == 50 + relabelled.shape[0]


def test_a_gate_that_never_fires_adds_no_hg_dagger_rows_and_bad_configs_are_refused():
    result, rows = _run(ExpertGate(1e9), "interventions")
    assert rows.shape[0] == 50 and [r.rows_collected for r in result.rounds[:-1]] == [0, 0]
    with pytest.raises(ValueError, match="needs a gate"):
        DAggerConfig(label="interventions")
    with pytest.raises(ValueError, match="all or interventions"):
        DAggerConfig(gate=ExpertGate(0.1), label="some")

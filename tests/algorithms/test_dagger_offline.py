"""End to end, from the LeRobot tutorial (docs/tutorials/lerobot.md): BC from a LeRobot dataset of CartPole expert episodes, then DAgger.

Offline start, interactive repair: the buffer starts as the recorded dataset (round 0),
DAgger extends it with relabelled rounds of the learner's own states, and the final
buffer (every round, with its flags) is written back as a LeRobot dataset. The test runs
the tutorial's block itself and checks the numbers it prints, then audits what it built.
"""

from __future__ import annotations

import torch

from imitrl import keys
from imitrl.datasets import load_lerobot
from imitrl.evaluation import evaluate
from tests._readme import assert_prints_what_it_promises, run


def test_readme_bc_from_lerobot_then_dagger(tmp_path):
    ns, printed = run("lerobot-example", tmp_path)
    assert_prints_what_it_promises("lerobot-example", printed)  # 153.3, then the expert's 500.0
    expert, env, demos, buffer = ns["expert"], ns["env"], ns["demos"], ns["buffer"]
    assert evaluate(ns["eval_env"], expert, 3, seed=1000).mean_return == 500.0

    data = buffer.data
    assert data[keys.ROUND].unique().tolist() == [0, 1, 2, 3]
    for k in demos.keys(True, True):  # round 0 is the recorded dataset, value for value
        assert torch.equal(data[: len(demos)].get(k), demos.get(k)), k
    relabelled = data[data[keys.ROUND] > 0]
    assert torch.equal(
        relabelled[keys.EXPERT_ACTION], expert(relabelled.clone())[keys.EXPERT_ACTION]
    )
    assert not relabelled[keys.EXPERT_EXECUTED].any()  # beta = 0: the learner drove

    # the aggregated buffer, every round with its flags, came back from LeRobot intact
    back = load_lerobot(tmp_path / "cartpole_dagger", env=env).rows
    for k in data.keys(True, True):
        assert torch.equal(back.get(k), data.get(k)), k

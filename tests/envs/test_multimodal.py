"""The two-way obstacle task: geometry, expert, mode measurement, env contract."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, check_env_specs

from imitrl import keys
from imitrl.envs.multimodal import (
    INTENT,
    ObstacleGeometry,
    TwoWayObstacleEnv,
    decision_states,
    expert_modes,
    mode_fractions,
    passing_side,
    two_way_expert,
)
from imitrl.policies import BetaMixer, behaviour_policy
from imitrl.policies.experts import as_actor
from imitrl.runtime import rollout_episodes

DET = ExplorationType.DETERMINISTIC


def _expert_rows(episodes: int, seed: int = 0):
    env = TwoWayObstacleEnv(batch_size=(min(episodes, 256),), seed=seed)
    return rollout_episodes(
        env, as_actor(two_way_expert()), episodes, exploration=DET, max_steps=10_000
    )


def test_expert_succeeds_from_every_start_on_both_sides():
    rows = _expert_rows(1000)
    ends = rows[rows[(keys.NEXT, keys.DONE)].reshape(-1)]
    assert ends.shape[0] == 1000
    assert (ends[(keys.NEXT, keys.REWARD)] == 1).all()
    assert (rows[keys.STEP].max() + 1) == ObstacleGeometry().steps == 40
    side = passing_side(rows)
    starts = rows[rows[keys.STEP] == 0]
    assert side.abs().min() == 1
    # symmetric task: about half above (binomial, 1000 episodes, 4 sd band)
    above = int((side > 0).sum())
    assert abs(above - 500) < 4 * (1000 * 0.25) ** 0.5
    assert starts[keys.OBSERVATION][:, 0].eq(0).all()
    assert starts[keys.OBSERVATION][:, 1].abs().max() <= ObstacleGeometry().band


class _Scripted(TensorDictModuleBase):
    """Straight ahead for ``delay`` steps, then the expert's action (intent +1)."""

    def __init__(self, delay: int) -> None:
        super().__init__()
        self.delay = delay
        self.in_keys, self.out_keys = [keys.OBSERVATION, INTENT], [keys.ACTION]
        self.expert = two_way_expert()

    def forward(self, td):
        td = self.expert(td)
        steps = torch.round(td[keys.OBSERVATION][..., 0] / ObstacleGeometry().dx)
        act = torch.where((steps < self.delay)[..., None], 0.0, td[keys.EXPERT_ACTION])
        td.set(keys.ACTION, act)
        return td


@pytest.mark.parametrize(("delay", "success"), [(0, True), (2, True), (3, False), (40, False)])
def test_hesitating_at_the_start_hits_the_disc(delay, success):
    # starts near the centre line: waiting three steps before steering is fatal
    env = TwoWayObstacleEnv(batch_size=(400,), seed=1)
    policy = behaviour_policy(two_way_expert(), _Scripted(delay), BetaMixer(0.0))
    rows = rollout_episodes(env, policy, 400, exploration=DET, max_steps=10_000)
    start_y = rows[rows[keys.STEP] == 0][keys.OBSERVATION][:, 1]
    reward = rows[(keys.NEXT, keys.REWARD)].reshape(-1)
    won = torch.stack([reward[rows[keys.EPISODE] == e].sum() > 0 for e in range(400)])
    central = start_y.abs() < 0.01
    assert int(central.sum()) > 50
    assert bool((won[central] == success).all())


def test_expert_modes_at_the_decision_states_are_plus_minus_half():
    obs = decision_states(100, seed=3)
    assert obs.shape == (100, 2)
    modes = expert_modes(obs)
    assert torch.equal(modes, torch.tensor([[-0.5, 0.5]]).expand(100, 2))
    # out of the band the expert keeps to its side whatever its intent
    far = torch.tensor([[0.5, 0.2], [0.5, -0.2]])
    assert torch.equal(expert_modes(far)[:, 0], expert_modes(far)[:, 1])


def test_mode_fractions_exact():
    obs = decision_states(8)
    up = torch.full((8, 1), 0.5)
    assert mode_fractions(obs, up) == {"above": 1.0, "below": 0.0, "neither": 0.0, "middle": 0.0}
    mean = torch.zeros(8, 1)
    assert mode_fractions(obs, mean) == {"above": 0.0, "below": 0.0, "neither": 1.0, "middle": 1.0}
    mixed = torch.tensor([[0.45], [-0.6], [1.0], [-1.0], [0.1], [0.5], [-0.5], [0.8]])
    f = mode_fractions(obs, mixed)
    assert f == {"above": 2 / 8, "below": 2 / 8, "neither": 4 / 8, "middle": 1 / 8}
    with pytest.raises(ValueError, match="actions"):
        mode_fractions(obs, torch.zeros(8))
    with pytest.raises(ValueError, match="too wide"):
        mode_fractions(obs, up, tol=0.6)


def test_env_contract_and_reproducibility():
    check_env_specs(TwoWayObstacleEnv(seed=0))  # unbatched
    env = TwoWayObstacleEnv(batch_size=(4,), seed=0)
    check_env_specs(env)
    a = _expert_rows(20, seed=7)
    b = _expert_rows(20, seed=7)
    c = _expert_rows(20, seed=8)
    assert torch.equal(a[keys.OBSERVATION], b[keys.OBSERVATION])
    assert not torch.equal(a[keys.OBSERVATION][:5], c[keys.OBSERVATION][:5])
    td = env.reset()
    with pytest.raises(ValueError, match="float actions"):
        env.step(td.set(keys.ACTION, torch.zeros(4, 1, dtype=torch.int64)))


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="band"):
        ObstacleGeometry(band=0.5)
    with pytest.raises(ValueError, match="disc"):
        ObstacleGeometry(obstacle_x=1.9, radius=0.3)
    with pytest.raises(ValueError, match="expert_speed"):
        ObstacleGeometry(expert_speed=2.0)
    expert = two_way_expert()
    bad = TensorDict(
        {keys.OBSERVATION: torch.zeros(3, 2), INTENT: torch.tensor([1, 0, -1])}, batch_size=[3]
    )
    with pytest.raises(ValueError, match="intent"):
        expert(bad)

"""The forking corridor: expert, the two ways to fail, outcome and mode diagnostics, env contract."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, check_env_specs

from imitrl import keys
from imitrl.envs.corridor import (
    OUTCOMES,
    ROUTE,
    CorridorGeometry,
    ForkingCorridorEnv,
    averaging_policy,
    corridor_expert,
    decision_states,
    expert_modes,
    mode_fractions,
    outcomes,
    reversals,
    switching_policy,
)
from imitrl.policies import BetaMixer, behaviour_policy
from imitrl.policies.experts import as_actor
from imitrl.runtime import rollout_episodes

DET = ExplorationType.DETERMINISTIC
EPISODES = 400


def _rows(policy, seed: int = 0, episodes: int = EPISODES):
    env = ForkingCorridorEnv(batch_size=(200,), seed=seed)
    # the expert rides along (beta = 0) so that every row carries its label
    behaviour = behaviour_policy(corridor_expert(), policy, BetaMixer(0.0))
    return rollout_episodes(env, behaviour, episodes, exploration=DET, max_steps=10_000)


def _fractions(codes: torch.Tensor) -> torch.Tensor:
    return torch.bincount(codes, minlength=len(OUTCOMES)).float() / codes.numel()


def test_expert_drives_the_route_it_drew_and_each_route_is_a_quarter():
    env = ForkingCorridorEnv(batch_size=(EPISODES,), seed=2)
    steps = CorridorGeometry().steps
    td = env.rollout(steps + 1, as_actor(corridor_expert()), break_when_any_done=True)
    assert td.shape == (EPISODES, steps) == (EPISODES, 40)  # nobody ends early
    final_y = td[(keys.NEXT, keys.OBSERVATION)][:, -1, 1].contiguous()
    lane = torch.bucketize(final_y, torch.tensor([-0.5, 0.0, 0.5]))
    assert torch.equal(lane, td[ROUTE][:, 0])
    assert bool((td[(keys.NEXT, keys.REWARD)][:, -1] == 1).all())
    # the same through outcomes(): every episode in a lane, each lane about 1/4
    f = _fractions(outcomes(_rows(as_actor(corridor_expert()), seed=2)))
    assert f[4:].sum() == 0
    sd = (0.25 * 0.75 / EPISODES) ** 0.5
    assert bool(((f[:4] - 0.25).abs() < 4 * sd).all()), f


def test_averaging_drives_into_the_first_divider():
    """The mean of the four routes' actions is 0 in the band: it never steers."""
    rows = _rows(averaging_policy())
    assert _fractions(outcomes(rows))[OUTCOMES.index("hit_fork1")] == 1.0
    assert reversals(rows) == 0.0
    f = mode_fractions(decision_states(200, fork=1), averaging_policy()(_obs(1)).get(keys.ACTION))
    assert f["middle"] == 1.0 and f["down"] == f["up"] == 0.0


def test_switching_routes_every_step_dithers_into_the_dividers():
    """Every action is one of the expert's, yet drawn afresh per step: it turns back in the
    decision windows and hits the dividers, at both forks."""
    rows = _rows(switching_policy(seed=1))
    f = _fractions(outcomes(rows))
    assert f[:4].sum() < 0.6
    assert f[OUTCOMES.index("hit_fork1")] > 0.15 and f[OUTCOMES.index("hit_fork2")] > 0.1
    assert reversals(rows) > 1.0
    assert reversals(_rows(as_actor(corridor_expert()))) == 0.0
    for fork in (1, 2):
        obs = decision_states(1000, fork=fork, seed=fork)
        td = switching_policy(seed=0)(TensorDict({keys.OBSERVATION: obs}, [1000]))
        m = mode_fractions(obs, td.get(keys.ACTION))
        assert m["neither"] == 0.0 and abs(m["up"] - 0.5) < 0.07, m


def _obs(fork: int) -> TensorDict:
    return TensorDict({keys.OBSERVATION: decision_states(200, fork=fork)}, [200])


def test_expert_modes_at_both_forks():
    for fork in (1, 2):
        modes = expert_modes(decision_states(50, fork=fork, seed=4))
        assert torch.equal(modes, torch.tensor([[-0.5, 0.5]]).expand(50, 2))
    obs = decision_states(50, fork=2)
    assert bool((obs[:, 0] == CorridorGeometry().turn2_x).all())
    assert bool(((obs[:, 1].abs() - 0.5).abs() <= 0.05).all())
    # the expert's own actions there, with a route per state: half down, half up, per fork
    route = torch.arange(200) % 4
    for fork in (1, 2):
        obs = decision_states(200, fork=fork)
        td = corridor_expert()(TensorDict({keys.OBSERVATION: obs, ROUTE: route}, [200]))
        m = mode_fractions(obs, td.get(keys.EXPERT_ACTION))
        assert m == {"down": 0.5, "up": 0.5, "neither": 0.0, "middle": 0.0}


def test_env_contract_reproducibility_and_bad_input():
    check_env_specs(ForkingCorridorEnv(seed=0))
    check_env_specs(ForkingCorridorEnv(batch_size=(3,), seed=0))
    a, b = (
        _rows(switching_policy(seed=5), episodes=20),
        _rows(switching_policy(seed=5), episodes=20),
    )
    assert torch.equal(a[keys.OBSERVATION], b[keys.OBSERVATION])
    with pytest.raises(ValueError, match="band"):
        CorridorGeometry(band=0.2)
    with pytest.raises(ValueError, match="fork1_x"):
        CorridorGeometry(fork2_x=1.0)
    with pytest.raises(ValueError, match="fork"):
        decision_states(5, fork=3)
    bad = TensorDict({keys.OBSERVATION: torch.zeros(2, 2), ROUTE: torch.tensor([0, 4])}, [2])
    with pytest.raises(ValueError, match="route"):
        corridor_expert()(bad)

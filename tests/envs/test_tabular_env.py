"""TabularEnv: TorchRL contract, gymnasium fidelity, kernel statistics, bad input."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

from imitrl.envs import TabularEnv
from imitrl.tabular import TabularMDP, expected_episode_length, success_probability
from tests._stats import chi_square_pvalue


@pytest.mark.parametrize("batch_size", [(), (5,)])
@pytest.mark.parametrize("rng", ["torch", "gymnasium"])
def test_check_env_specs(lake, batch_size, rng):
    check_env_specs(TabularEnv(lake, batch_size=batch_size, rng=rng, seed=0))


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [
        ("FrozenLake-v1", {}),
        ("FrozenLake-v1", {"map_name": "8x8"}),
        ("FrozenLake-v1", {"desc": ["SFFH", "FHFF", "FFFF", "HFFG"], "success_rate": 0.5}),
        ("CliffWalking-v1", {"max_episode_steps": 60}),
    ],
)
def test_batch_one_reproduces_gymnasium_step_for_step(env_id, kwargs):
    genv = gym.make(env_id, **kwargs)
    mdp = TabularMDP.from_gym(genv, 0.9)
    env = TabularEnv(mdp, rng="gymnasium", seed=123)
    td = env.reset()
    s, _ = genv.reset(seed=123)
    assert int(td["observation"]) == s
    actions = np.random.default_rng(0).integers(0, mdp.num_actions, 3000)
    episodes = 0
    for t, a in enumerate(actions.tolist()):
        td["action"] = torch.tensor(a)
        out, td = env.step_and_maybe_reset(td)
        s2, r, term, trunc, _ = genv.step(a)
        nxt = out["next"]
        got = (
            int(nxt["observation"]),
            float(nxt["reward"]),
            bool(nxt["terminated"]),
            bool(nxt["truncated"]),
        )
        assert got == (s2, float(r), term, trunc), f"step {t}"
        if term or trunc:
            episodes += 1
            s2, _ = genv.reset()
        assert int(td["observation"]) == s2, f"after step {t}"
    assert episodes > 20


def test_same_seed_same_rollout_and_different_seed_differs(lake, expert_table):
    def roll(seed):
        env = TabularEnv(lake, batch_size=(64,), seed=seed)
        return env.rollout(200, _table_policy(expert_table), break_when_any_done=False)

    a, b, c = roll(3), roll(3), roll(4)
    assert torch.equal(a["next", "observation"], b["next", "observation"])
    assert not torch.equal(a["next", "observation"], c["next", "observation"])


def _table_policy(table):
    from tensordict.nn import TensorDictModule

    class Lookup(torch.nn.Module):
        def __init__(self, t):
            super().__init__()
            self.register_buffer("t", t)

        def forward(self, obs):
            return self.t[obs]

    return TensorDictModule(Lookup(table), in_keys=["observation"], out_keys=["action"])


def test_one_step_frequencies_match_the_kernel(lake):
    """Chi-square goodness of fit of s' | (s, a) for every non-terminal pair visited."""
    env = TabularEnv(lake, batch_size=(20000,), seed=11)
    td = env.rollout(40, policy=None, break_when_any_done=False)  # uniform random actions
    s = td["observation"].reshape(-1)
    a = td["action"].reshape(-1)
    s2 = td["next", "observation"].reshape(-1)
    counts = torch.zeros(16, 4, 16)
    counts.index_put_((s, a, s2), torch.ones_like(s, dtype=torch.float32), accumulate=True)
    pvals = []
    for si in range(16):
        if lake.terminal[si]:
            continue
        for ai in range(4):
            n = counts[si, ai].sum()
            if n < 500:
                continue
            p = lake.P[si, ai]
            support = p > 0
            assert counts[si, ai][~support].sum() == 0, (si, ai)
            pvals.append(chi_square_pvalue(counts[si, ai][support].double(), n * p[support]))
    assert len(pvals) >= 30
    # Bonferroni over all pairs at family-wise level 1e-3
    assert min(pvals) > 1e-3 / len(pvals)


def test_time_limit_truncates_like_gymnasium():
    # a two-state loop that never terminates: every episode is cut at max_steps
    P = np.zeros((2, 1, 2))
    P[0, 0, 1] = P[1, 0, 0] = 1.0
    mdp = TabularMDP.from_arrays(P, np.ones((2, 1)), 1.0, max_steps=7)
    env = TabularEnv(mdp, batch_size=(3,), seed=0)
    td = env.rollout(20, policy=None, break_when_any_done=False)
    trunc = td["next", "truncated"].squeeze(-1)
    assert trunc[:, 6].all() and trunc[:, 13].all() and int(trunc.sum()) == 6
    assert not td["next", "terminated"].any()
    assert torch.equal(td["next", "done"], td["next", "truncated"])


def test_collector_runs_on_tabular_env(lake, expert_table):
    env = TabularEnv(lake, batch_size=(16,), seed=0)
    collector = Collector(
        env,
        _table_policy(expert_table),
        frames_per_batch=16 * 50,
        total_frames=16 * 100,
        auto_register_policy_transforms=False,
    )
    frames = 0
    for batch in collector:
        frames += batch.numel()
        assert batch["action"].dtype == torch.int64
        assert torch.equal(batch["action"], expert_table[batch["observation"]])
    collector.shutdown()
    assert frames == 1600


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (torch.tensor([0, 4, 1]), r"action 4 is outside \[0, 4\)"),
        (torch.tensor([0, -1, 1]), r"action -1 is outside \[0, 4\)"),
        (torch.tensor([0.0, 1.0, 2.0]), "integer actions"),
    ],
)
def test_bad_actions_raise(lake, action, match):
    env = TabularEnv(lake, batch_size=(3,), seed=0)
    td = env.reset().set("action", action)
    with pytest.raises(ValueError, match=match):
        env.step(td)


def test_wrong_shaped_action_raises(lake):
    env = TabularEnv(lake, seed=0)
    td = env.reset().set("action", torch.tensor([0, 1]))
    with pytest.raises(ValueError, match=r"one action per lane, shape \(\)"):
        env.step(td)


def test_bad_constructor_arguments(lake):
    with pytest.raises(ValueError, match="rng must be one of"):
        TabularEnv(lake, rng="numpy")
    with pytest.raises(ValueError, match="batch_size must be"):
        TabularEnv(lake, batch_size=(2, 3))
    with pytest.raises(ValueError, match="max_steps"):
        TabularEnv(lake, max_steps=0)


def test_play_tables_matches_exact_values_and_is_seeded(lake, expert_table):
    clone = torch.tensor([0, 0, 0, 0, 0, 0, 0, 0, 3, 1, 0, 0, 0, 0, 1, 0])
    tables = torch.stack([expert_table, clone])
    env = TabularEnv(lake, batch_size=(1,), seed=5)
    out = env.play_tables(tables, 40_000)
    for k, table in enumerate(tables):
        p = success_probability(lake, table)
        rate = out["success"][k].double().mean()
        assert abs(rate - p) < 4 * (p * (1 - p) / 40_000) ** 0.5
        assert abs(out["lengths"][k].double().mean() - expected_episode_length(lake, table)) < 0.5
    assert torch.equal(out["returns"], out["success"].double())  # FrozenLake pays 1 on success
    again = TabularEnv(lake, batch_size=(1,), seed=5).play_tables(tables, 40_000)
    assert all(torch.equal(out[key], again[key]) for key in out)
    with pytest.raises(ValueError, match=r"shape \[K, 16\]"):
        env.play_tables(torch.zeros(2, 15, dtype=torch.long), 3)
    with pytest.raises(ValueError, match=r"lie in \[0, 4\)"):
        env.play_tables(torch.full((16,), 4), 3)
    with pytest.raises(ValueError, match="gymnasium's stream"):
        TabularEnv(lake, rng="gymnasium", seed=0).play_tables(expert_table, 3)


def test_replicated_mdp_with_pinned_lanes(lake, expert_table):
    K = 3
    product = lake.replicate(K)
    assert product.num_states == 48 and float(product.initial.sum()) == pytest.approx(1.0)
    assert success_probability(product, expert_table.repeat(K)) == pytest.approx(
        success_probability(lake, expert_table), abs=1e-12
    )
    starts = torch.arange(K).repeat_interleave(4) * 16
    env = TabularEnv(product, batch_size=(12,), seed=0, initial_state=starts)
    td = env.rollout(60, policy=None, break_when_any_done=False)
    copy = td["observation"] // 16
    assert torch.equal(
        copy, (torch.arange(12) // 4)[:, None].expand_as(copy)
    )  # lanes never leave their copy
    with pytest.raises(ValueError, match="initial_state must be an integer tensor of shape"):
        TabularEnv(product, batch_size=(12,), initial_state=torch.zeros(5, dtype=torch.long))
    with pytest.raises(ValueError, match="cannot be combined"):
        TabularEnv(product, batch_size=(12,), rng="gymnasium", initial_state=starts)

"""DemonstrationBuffer: grows without loss, reloads identically, rejects bad rows."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.envs import TabularEnv
from imitrl.learners import TaskSpec, build
from imitrl.policies import Expert


def rows(n, first_episode=0, round_index=0, seed=0, obs_dtype=torch.int64):
    g = torch.Generator().manual_seed(seed)
    a = torch.randint(0, 4, (n,), generator=g)
    obs = torch.randint(0, 16, (n,), generator=g).to(obs_dtype)
    return TensorDict(
        {
            keys.OBSERVATION: obs,
            keys.EXPERT_ACTION: a,
            keys.ACTION: a.clone(),
            keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
            keys.EPISODE: first_episode + torch.arange(n) // 5,
            keys.ROUND: torch.full((n,), round_index),
            keys.STEP: torch.arange(n) % 5,
            (keys.NEXT, keys.REWARD): torch.zeros(n, 1),
        },
        [n],
    )


def cont(a: torch.Tensor, episode: int = 0) -> TensorDict:
    """One episode of rows with continuous actions ``a`` [n, d] and 3-dim observations."""
    n = a.shape[0]
    return TensorDict(
        {
            keys.OBSERVATION: torch.zeros(n, 3),
            keys.EXPERT_ACTION: a,
            keys.ACTION: a.clone(),
            keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
            keys.EPISODE: torch.full((n,), episode, dtype=torch.long),
            keys.ROUND: torch.zeros(n, dtype=torch.long),
            keys.STEP: torch.arange(n),
        },
        [n],
    )


def test_k_rounds_hold_exactly_their_union_and_reload_identically(tmp_path):
    buf = DemonstrationBuffer(capacity=8)
    parts = []
    for k, n in enumerate([7, 1, 9, 16, 33, 2]):  # crosses several capacity doublings
        part = rows(n, first_episode=buf.next_episode, round_index=k, seed=k)
        parts.append(part)
        buf.extend(part)
    union = torch.cat(parts)
    assert len(buf) == union.shape[0] == 68
    assert (buf.data == union).all()
    assert list(buf.rounds()) == list(range(6))
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))
    fit_bc(learner, buf, BCConfig(num_steps=5))
    buf.save(tmp_path / "demo", learner=learner, state={"round": 5, "beta": 0.25})
    twin = build("cross_entropy", TaskSpec(action=4, num_states=16))
    again, state = DemonstrationBuffer.load(tmp_path / "demo", learner=twin)
    assert state == {"round": 5, "beta": 0.25}
    for a, b in zip(learner.state_dict().values(), twin.state_dict().values()):
        assert torch.equal(a, b)
    assert twin.opt_pi.state_dict()["state"][0]["step"] == 5  # the optimizer resumes too
    assert (again.data == union).all() and again.schema == buf.schema
    assert again.next_episode == buf.next_episode
    again.extend(rows(3, first_episode=again.next_episode, round_index=6))  # still growable
    assert len(again) == 71 and (again.data[:68] == union).all()


def test_fit_and_dagger_extend_the_same_buffer_without_loss(lake, expert_table):
    env = TabularEnv(lake, batch_size=(3,), seed=0)
    expert = Expert.from_table(expert_table)
    buf = DemonstrationBuffer(num_states=16, capacity=4, action_spec=Categorical(4))
    from torchrl.envs.utils import ExplorationType

    from imitrl.runtime import rollout_episodes

    demos = rollout_episodes(
        env, expert.as_actor(), 3, exploration=ExplorationType.DETERMINISTIC, max_steps=10_000
    )
    buf.extend(demos)
    snapshot = buf.data.clone()
    res = dagger(
        EnvSource(env),
        expert,
        lambda: build("cross_entropy", TaskSpec(action=4, num_states=16)),
        buf,
        DAggerConfig(rounds=3, bc=BCConfig(num_steps=50)),
    )
    assert (buf.data[: snapshot.shape[0]] == snapshot).all()
    assert len(buf) == snapshot.shape[0] + sum(r.rows_collected for r in res.rounds)
    assert [r.rows_trained for r in res.rounds] == [
        snapshot.shape[0] + sum(x.rows_collected for x in res.rounds[:k]) for k in range(3)
    ]


def test_sampling_is_seeded():
    def draw(seed):
        b = DemonstrationBuffer(generator=torch.Generator().manual_seed(seed), batch_size=10)
        b.extend(rows(50))
        return torch.cat([b.sample()[keys.OBSERVATION] for _ in range(5)])

    assert torch.equal(draw(1), draw(1)) and not torch.equal(draw(1), draw(2))


def test_empty_buffer_errors(lake):
    buf = DemonstrationBuffer()
    with pytest.raises(ValueError, match="empty"):
        _ = buf.data
    with pytest.raises(ValueError, match="empty"):
        buf.sample(4)
    with pytest.raises(ValueError, match="empty"):
        fit_bc(build("cross_entropy", TaskSpec(action=4, num_states=16)), buf)
    with pytest.raises(ValueError, match="empty"):
        dagger(
            EnvSource(TabularEnv(lake)),
            Expert.from_table(torch.zeros(16, dtype=torch.long)),
            lambda: build("cross_entropy", TaskSpec(action=4, num_states=16)),
            buf,
        )
    with pytest.raises(ValueError, match="zero rows"):
        buf.extend(rows(0))


def test_schema_changes_are_rejected_and_nothing_is_written():
    buf = DemonstrationBuffer()
    buf.extend(rows(10))
    extra = rows(4, first_episode=buf.next_episode)
    extra.set("task", torch.zeros(4, dtype=torch.long))
    with pytest.raises(ValueError, match="unexpected key 'task'"):
        buf.extend(extra)
    missing = rows(4, first_episode=buf.next_episode).exclude((keys.NEXT, keys.REWARD))
    with pytest.raises(ValueError, match=r"missing key 'next\.reward'"):
        buf.extend(missing)
    with pytest.raises(ValueError, match="'observation' is float32"):
        buf.extend(rows(4, first_episode=buf.next_episode, obs_dtype=torch.float32))
    no_label = rows(4, first_episode=buf.next_episode).exclude(keys.EXPERT_ACTION)
    with pytest.raises(ValueError, match="missing required keys"):
        buf.extend(no_label)
    assert len(buf) == 10


def test_bad_values_are_rejected():
    buf = DemonstrationBuffer(action_spec=Categorical(4), num_states=16)
    bad = rows(5)
    bad.set(keys.EXPERT_ACTION, torch.tensor([0, 1, 4, 0, 0]))
    with pytest.raises(ValueError, match=r"'expert_action' holds action 4, outside \[0, 4\)"):
        buf.extend(bad)
    with pytest.raises(ValueError, match=r"integer states in \[0, 16\)"):
        buf.extend(rows(5).set(keys.OBSERVATION, torch.tensor([0, 1, 16, 0, 0])))
    nan = rows(5)
    nan.set((keys.NEXT, keys.REWARD), torch.tensor([[0.0], [float("nan")], [0.0], [0.0], [0.0]]))
    with pytest.raises(ValueError, match="NaN or inf"):
        buf.extend(nan)
    buf.extend(rows(5))
    with pytest.raises(ValueError, match="episode id 0 is already used"):
        buf.extend(rows(5))


def test_continuous_actions_checked_against_bounds_and_shape():
    spec = Bounded(-1.0, 1.0, shape=(2,))
    buf = DemonstrationBuffer(action_spec=spec)

    with pytest.raises(ValueError, match="outside the bounds"):
        buf.extend(cont(torch.tensor([[0.0, 1.5]])))
    with pytest.raises(ValueError, match="expected"):
        buf.extend(cont(torch.zeros(2, 3)))
    nan_obs = cont(torch.zeros(2, 2))
    nan_obs.set(keys.OBSERVATION, torch.tensor([[0.0, float("nan"), 0.0], [0.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="NaN or inf under 'observation'"):
        buf.extend(nan_obs)
    buf.extend(cont(torch.zeros(2, 2)))
    assert len(buf) == 2


def test_load_errors(tmp_path):
    with pytest.raises(ValueError, match="not a saved DemonstrationBuffer"):
        DemonstrationBuffer.load(tmp_path)
    buf = DemonstrationBuffer()
    buf.extend(rows(6))
    buf.save(tmp_path / "ok")
    with pytest.raises(ValueError, match="cannot load"):  # no learner was saved
        DemonstrationBuffer.load(
            tmp_path / "ok", learner=build("cross_entropy", TaskSpec(action=4, num_states=16))
        )
    (tmp_path / "ok" / "manifest.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"manifest\.json: not JSON"):
        DemonstrationBuffer.load(tmp_path / "ok")
    with pytest.raises(ValueError, match="empty"):
        DemonstrationBuffer().save(tmp_path / "empty")


def test_discrete_action_shape_other_specs_and_episode_blocks():
    from torchrl.data import OneHot

    buf = DemonstrationBuffer(action_spec=Categorical(4))
    wide = rows(4)
    wide.set(keys.EXPERT_ACTION, wide[keys.EXPERT_ACTION][:, None])
    wide.set(keys.ACTION, wide[keys.ACTION][:, None])
    with pytest.raises(ValueError, match=r"rows have shape \(1,\)"):
        buf.extend(wide)
    split = rows(6)
    split.set(keys.EPISODE, torch.tensor([0, 0, 1, 1, 0, 0]))
    with pytest.raises(ValueError, match="contiguous"):
        buf.extend(split)
    onehot = DemonstrationBuffer(action_spec=OneHot(4))
    good = rows(3)
    a = torch.nn.functional.one_hot(torch.tensor([0, 1, 2]), 4).bool()
    good.set(keys.EXPERT_ACTION, a)
    good.set(keys.ACTION, a.clone())
    bad = good.clone()
    bad[keys.EXPERT_ACTION][2] = torch.tensor([True, True, False, False])
    with pytest.raises(ValueError, match="outside OneHot"):
        onehot.extend(bad)
    onehot.extend(good)
    assert len(onehot) == 3


def test_action_dtype_must_be_the_specs_and_batched_bounds_are_per_lane():
    """Labels in another dtype than the spec's are refused at extend, not rounds later in DAgger."""
    discrete = DemonstrationBuffer(action_spec=Categorical(4))
    wrong = rows(10)
    wrong.set(keys.EXPERT_ACTION, wrong.get(keys.EXPERT_ACTION).to(torch.int32))
    wrong.set(keys.ACTION, wrong.get(keys.ACTION).to(torch.int32))
    with pytest.raises(
        ValueError, match=r"dtype torch\.int32, the action spec expects torch\.int64"
    ):
        discrete.extend(wrong)
    assert len(discrete) == 0

    box = Bounded(-1.0, 1.0, shape=(2,))
    with pytest.raises(
        ValueError, match=r"dtype torch\.int64, the action spec expects torch\.float32"
    ):
        DemonstrationBuffer(action_spec=box).extend(cont(torch.zeros(5, 2, dtype=torch.long)))
    # a batched env's spec ([8, 2]) checks each row against one lane's bounds, any row count
    lanes = Bounded(-torch.ones(8, 2), torch.ones(8, 2), shape=(8, 2))
    buf = DemonstrationBuffer(action_spec=lanes)
    buf.extend(cont(torch.full((50, 2), 0.5)))
    assert len(buf) == 50
    with pytest.raises(ValueError, match="outside the bounds"):
        buf.extend(cont(torch.full((3, 2), 1.5), episode=1))
    uneven = Bounded(-torch.rand(8, 2) - 1, torch.ones(8, 2), shape=(8, 2))
    with pytest.raises(ValueError, match="action_spec_unbatched"):
        DemonstrationBuffer(action_spec=uneven).extend(cont(torch.zeros(4, 2)))


def test_sampling_another_batch_size_than_the_constructors_is_silent():
    """A review: the in-memory buffer leaked TorchRL's "conflicting batch_sizes" warning for
    sample(batch_size), its documented API (the disk buffer was silent)."""
    import warnings

    buf = DemonstrationBuffer(batch_size=4)
    buf.extend(_rows_for_sampling())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert buf.sample(8).shape == (8,) and buf.sample().shape == (4,)


def _rows_for_sampling():
    from tests.data.test_disk import cartpole_rows

    return cartpole_rows(20)

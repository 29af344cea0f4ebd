"""Chunk-aware DAgger (issue 46): at every state a learner-driven round visits, the expert's
own next H actions from that state, played on the simulator and undone. A chunked
learner's relabelled rows then carry whole chunks (today's windowing keeps one label of
each); planning leaves the episode as it was; a plan is what the expert does from there."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, dagger
from imitrl.algorithms.dagger import EnvSource
from imitrl.algorithms.expert_plan import ExpertPlanner, with_plans
from imitrl.data import DemonstrationBuffer
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK, add_chunk_labels
from imitrl.envs import make_env
from imitrl.envs.multimodal import TwoWayObstacleEnv, two_way_expert
from imitrl.experts import pendulum_expert
from imitrl.learners import build
from imitrl.learners.chunks import CHUNK_HORIZON
from imitrl.runtime import paths, rollout_episodes

LIMIT = 40
H = CHUNK_HORIZON  # the chunked losses' horizon


def _run(env_id: str, plans: bool, seed: int = 0):
    """DAgger, 2 rounds (round 1: the learner drives, beta 0), a chunked learner."""
    env = make_env(env_id, seed=seed, max_episode_steps=LIMIT)
    expert = pendulum_expert()
    demos = rollout_episodes(env, expert, 1)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(with_plans(demos, H) if plans else demos)
    make = lambda: build("mse_chunk", env, hidden=(16,), seed=seed)  # noqa: E731
    source = EnvSource(env, exploration=ExplorationType.DETERMINISTIC, plans=plans)
    dagger(source, expert, make, buffer, DAggerConfig(rounds=2, episodes_per_round=2,
           bc=BCConfig(num_steps=20, batch_size=16), seed=seed))  # fmt: skip
    data = buffer.data
    return data[data.get(keys.ROUND) == 1]


def test_relabelled_rows_of_a_chunked_learner_carry_whole_chunks():
    rows = _run("Pendulum-v1", plans=True)
    assert not rows.get(keys.EXPERT_EXECUTED).any()  # the learner drove every step
    labelled = add_chunk_labels(rows, H)
    pad, plan = labelled.get(CHUNK_PAD), labelled.get(EXPERT_CHUNK)
    left = LIMIT - rows.get(keys.STEP)  # steps left in the episode, this one included
    want_pad = torch.arange(H)[None, :] >= left[:, None]
    assert torch.equal(pad, want_pad)  # whole chunks, padded only past the episode's end
    assert int((~pad).sum()) > rows.shape[0] * (H - 1)
    assert torch.equal(plan[:, 0], rows.get(keys.EXPERT_ACTION))  # its own label first
    windowed = add_chunk_labels(rows.exclude(keys.EXPERT_PLAN, keys.EXPERT_PLAN_PAD), H)
    assert bool(windowed.get(CHUNK_PAD)[:, 1:].all())  # what masking keeps: entry 0 alone


def test_a_plan_is_what_the_expert_does_from_that_state():
    """Checked without snapshots: a fresh env with the run's seed replays the executed
    actions (the demonstration, then round 1's first episode up to step 5), and the
    expert drives from there: the same actions, bit for bit."""
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=LIMIT)
    demo = rollout_episodes(env, pendulum_expert(), 1)
    rows = _run("Pendulum-v1", plans=True)
    first = rows[rows.get(keys.EPISODE) == rows.get(keys.EPISODE).min()]
    replay = make_env("Pendulum-v1", seed=0, max_episode_steps=LIMIT)
    expert = pendulum_expert()
    expert.bind(replay.action_spec_unbatched)
    td = replay.reset()
    for action in demo.get(keys.ACTION):  # the demonstration's episode, to its end
        td = replay.step(td.set(keys.ACTION, action)).get(keys.NEXT)
    replay.reset()  # the rollout's reset as the demonstration ended, then the round's
    td = replay.reset()
    assert torch.equal(td.get(keys.OBSERVATION), first.get(keys.OBSERVATION)[0])
    for action in first.get(keys.ACTION)[:5]:  # the learner's first 5 steps
        td = replay.step(td.set(keys.ACTION, action)).get(keys.NEXT)
    assert torch.equal(td.get(keys.OBSERVATION), first.get(keys.OBSERVATION)[5])
    actions = []
    for _ in range(H):
        td = expert.as_actor()(td)
        actions.append(td.get(keys.ACTION))
        td = replay.step(td).get(keys.NEXT)
    assert torch.equal(torch.stack(actions), first.get(keys.EXPERT_PLAN)[5])


def test_planning_leaves_the_episodes_as_they_were():
    with_plans_rows = _run("Pendulum-v1", plans=True)
    without = _run("Pendulum-v1", plans=False)
    for key in (keys.OBSERVATION, keys.ACTION, keys.EXPERT_ACTION, keys.STEP):
        assert torch.equal(with_plans_rows.get(key), without.get(key)), key


def test_plans_on_an_env_of_imitrls_own_follow_its_hidden_choice():
    env = TwoWayObstacleEnv(seed=3)
    expert = two_way_expert()
    expert.bind(env.action_spec_unbatched)
    planner = ExpertPlanner(expert, env, H)
    with paths.reference():
        from tensordict.nn import TensorDictSequential

        actor = TensorDictSequential(expert.as_actor(), planner)
        rows = rollout_episodes(
            env, actor, 2, max_steps=200, exploration=ExplorationType.DETERMINISTIC
        )
    driven = add_chunk_labels(rows.exclude(keys.EXPERT_PLAN, keys.EXPERT_PLAN_PAD), H)
    assert torch.equal(rows.get(keys.EXPERT_PLAN), driven.get(EXPERT_CHUNK))
    assert torch.equal(rows.get(keys.EXPERT_PLAN_PAD), driven.get(CHUNK_PAD))


def test_what_cannot_plan_is_refused_with_one_line():
    env = make_env("Pendulum-v1", seed=0, num_envs=2, max_episode_steps=LIMIT)
    with pytest.raises(ValueError, match="one lane"):
        ExpertPlanner(pendulum_expert(), env, H)
    single = make_env("Pendulum-v1", seed=0, max_episode_steps=LIMIT)
    source = EnvSource(single, plans=True)
    with pytest.raises(ValueError, match="predicts one action"):
        source.check(pendulum_expert(), build("mse", single, hidden=(8,)))
    buffer = DemonstrationBuffer(action_spec=single.action_spec_unbatched)
    buffer.extend(rollout_episodes(single, pendulum_expert(), 1))
    make = lambda: build("mse_chunk", single, hidden=(8,))  # noqa: E731
    with pytest.raises(ValueError, match="with_plans"):
        dagger(source, pendulum_expert(), make, buffer, DAggerConfig(rounds=2))
    with pytest.raises(ValueError, match="expert drove"):
        with_plans(_run("Pendulum-v1", plans=False), H)

"""Action chunks: labels at episode ends, execution (receding horizon, ACT's ensembling),
DAgger's relabelled rows."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import ActionChunkTransform
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.data.chunks import (
    ACTION_CHUNK,
    CHUNK_PAD,
    EXPERT_CHUNK,
    IS_INIT,
    add_chunk_labels,
    chunk_labels,
)
from imitrl.envs import multimodal as mm
from imitrl.learners import build, registry
from imitrl.learners.task import TaskSpec
from imitrl.policies.chunking import ChunkedPolicy, ChunkExecution, chunk_env, ensemble_weights
from imitrl.policies.experts import as_actor
from imitrl.runtime import rollout_episodes

DET = ExplorationType.DETERMINISTIC


def test_chunk_labels_pad_and_mask_at_each_episodes_end_in_any_row_order():
    # episode 1: labels 0, 1, 2; episode 0: labels 3, 4, 5, 6 (steps 0..3); rows shuffled
    label = torch.arange(7.0).unsqueeze(-1)
    episode = torch.tensor([1, 1, 1, 0, 0, 0, 0])
    step = torch.tensor([0, 1, 2, 0, 1, 2, 3])
    perm = torch.tensor([3, 0, 6, 2, 5, 1, 4])
    chunk, pad = chunk_labels(label[perm], episode[perm], step[perm], 3)
    expected = {  # original row -> (chunk, pad)
        0: ([0, 1, 2], [0, 0, 0]),
        1: ([1, 2, 2], [0, 0, 1]),
        2: ([2, 2, 2], [0, 1, 1]),
        3: ([3, 4, 5], [0, 0, 0]),
        4: ([4, 5, 6], [0, 0, 0]),
        5: ([5, 6, 6], [0, 0, 1]),
        6: ([6, 6, 6], [0, 1, 1]),
    }
    for i, row in enumerate(perm.tolist()):
        assert chunk[i, :, 0].tolist() == expected[row][0]
        assert pad[i].tolist() == [bool(b) for b in expected[row][1]]


def test_chunk_labels_match_torchrls_action_chunk_transform_on_one_episode():
    g = torch.Generator().manual_seed(0)
    actions = torch.randn(9, 2, generator=g)
    chunk, pad = chunk_labels(actions, torch.zeros(9, dtype=torch.long), torch.arange(9), 4)
    td = TensorDict({"action": actions.unsqueeze(0)}, batch_size=[1, 9])
    out = ActionChunkTransform(4)(td)
    assert torch.equal(chunk, out.get(("vla_action", "chunk"))[0])
    assert torch.equal(pad, out.get("action_is_pad")[0])


def test_chunk_labels_refuse_gaps_and_missing_keys():
    with pytest.raises(ValueError, match="consecutive"):
        chunk_labels(
            torch.zeros(3, 1), torch.zeros(3, dtype=torch.long), torch.tensor([0, 1, 3]), 2
        )
    with pytest.raises(ValueError, match="positive integer"):
        chunk_labels(torch.zeros(3, 1), torch.zeros(3, dtype=torch.long), torch.arange(3), 0)
    rows = TensorDict({keys.EXPERT_ACTION: torch.zeros(3, 1)}, batch_size=[3])
    with pytest.raises(ValueError, match="episode"):
        add_chunk_labels(rows, 2)


def test_ensemble_weights_are_acts_exponential_oldest_first():
    w = ensemble_weights(3, 0.5)
    z = 1 + math.exp(-0.5) + math.exp(-1.0)
    assert torch.allclose(w, torch.tensor([1 / z, math.exp(-0.5) / z, math.exp(-1.0) / z]).double())
    assert torch.equal(ensemble_weights(4, 0.0), torch.full((4,), 0.25).double())


class _Counter(TensorDictModuleBase):
    """Writes a flat chunk ``[B, H]`` (m = 1): entry h of the call-c chunk is ``100 c + h``."""

    in_keys, out_keys = [keys.OBSERVATION], [keys.ACTION]

    def __init__(self, horizon: int) -> None:
        super().__init__()
        self.horizon, self.calls = horizon, 0

    def forward(self, td):
        self.calls += 1
        chunk = 100.0 * self.calls + torch.arange(self.horizon, dtype=torch.float32)
        td.set(keys.ACTION, chunk.expand(*td.batch_size, self.horizon).clone())
        return td


def _step(policy, init: bool, lanes: int = 1) -> torch.Tensor:
    td = TensorDict(
        {
            keys.OBSERVATION: torch.zeros(lanes, 2),
            IS_INIT: torch.full((lanes, 1), init),
        },
        batch_size=[lanes],
    )
    return policy(td).get(keys.ACTION)[:, 0]


def test_receding_horizon_executes_k_actions_then_replans_and_restarts_at_a_reset():
    policy = ChunkedPolicy(_Counter(4), 1, ChunkExecution(4, execute=2))
    acts = [_step(policy, i == 0).item() for i in range(5)]
    assert acts == [100, 101, 200, 201, 300]
    assert _step(policy, True).item() == 400  # a reset replans at once
    assert policy(
        TensorDict(
            {keys.OBSERVATION: torch.zeros(1, 2), IS_INIT: torch.zeros(1, 1, dtype=torch.bool)},
            [1],
        )
    ).get(ACTION_CHUNK).shape == (1, 4, 1)


def test_temporal_ensembling_averages_every_live_prediction_with_acts_weights():
    m = 0.3
    policy = ChunkedPolicy(_Counter(3), 1, ChunkExecution(3, ensemble=m))
    a = [_step(policy, i == 0).item() for i in range(4)]
    assert a[0] == 100  # one prediction
    # step 1: chunk 1 (oldest, i=0) says 101, chunk 2 (i=1) says 200
    w = ensemble_weights(2, m)
    assert a[1] == pytest.approx(float(w[0] * 101 + w[1] * 200), rel=1e-6)
    # step 3: chunks 2, 3, 4 (chunk 1 ran out) say 202, 301, 400
    w = ensemble_weights(3, m)
    assert a[3] == pytest.approx(float(w[0] * 202 + w[1] * 301 + w[2] * 400), rel=1e-6)
    assert _step(policy, True).item() == 500  # a reset forgets the old chunks


class _Echo(TensorDictModuleBase):
    """Writes the starting noise it was given (``POLICY_NOISE``) tiled over the chunk, or
    NaN without one; ``draw_noise`` counts its draws: 1, 2, 3, ..."""

    in_keys, out_keys = [keys.OBSERVATION], [keys.ACTION]

    def __init__(self, horizon: int) -> None:
        super().__init__()
        self.horizon, self.draws = horizon, 0

    def draw_noise(self, n: int) -> torch.Tensor:
        out = torch.arange(self.draws + 1, self.draws + n + 1, dtype=torch.float32)[:, None]
        self.draws += n
        return out

    def forward(self, td):
        noise = td.get(keys.POLICY_NOISE, torch.full((*td.batch_size, 1), float("nan")))
        td.set(keys.ACTION, noise.expand(*td.batch_size, self.horizon).clone())
        return td


@pytest.mark.parametrize("execution", [{"execute": 2}, {"ensemble": 0.1}])
def test_held_noise_is_drawn_once_per_episode_and_lane_and_passed_to_every_query(execution):
    policy = ChunkedPolicy(_Echo(4), 1, ChunkExecution(4, hold_noise=True, **execution))

    def step(init: list[bool]) -> list[float]:
        td = TensorDict(
            {
                keys.OBSERVATION: torch.zeros(len(init), 2),
                IS_INIT: torch.tensor(init)[:, None],
            },
            batch_size=[len(init)],
        )
        return pytest.approx(policy(td).get(keys.ACTION)[:, 0].tolist(), rel=1e-6)

    assert step([True, True, True]) == [1.0, 2.0, 3.0]  # one draw per lane
    for _ in range(6):  # replans (every 2 steps, or every step) reuse the episode's draw
        assert step([False, False, False]) == [1.0, 2.0, 3.0]
    assert step([False, True, False]) == [1.0, 4.0, 3.0]  # lane 1's reset draws again
    assert step([False, False, False]) == [1.0, 4.0, 3.0]
    # without hold_noise the network draws for itself (here: no noise passed at all)
    plain = ChunkedPolicy(_Echo(4), 1, ChunkExecution(4, execute=2))
    td = TensorDict(
        {keys.OBSERVATION: torch.zeros(1, 2), IS_INIT: torch.ones(1, 1, dtype=torch.bool)}, [1]
    )
    assert math.isnan(plain(td).get(keys.ACTION).item())


def test_held_noise_needs_a_network_that_draws_noise():
    with pytest.raises(ValueError, match="draw_noise"):
        ChunkedPolicy(_Counter(2), 1, ChunkExecution(2, hold_noise=True))


def test_a_chunked_policy_without_is_init_fails_loudly():
    policy = ChunkedPolicy(_Counter(2), 1, ChunkExecution(2))
    with pytest.raises(ValueError, match="chunk_env"):
        policy(TensorDict({keys.OBSERVATION: torch.zeros(1, 2)}, [1]))
    with pytest.raises(ValueError, match="execute must be in"):
        ChunkExecution(2, execute=3)


def test_dagger_with_chunks_labels_each_visited_state_and_chunks_the_relabelled_rows():
    torch.manual_seed(0)
    task = TaskSpec(action=mm.TwoWayObstacleEnv().action_spec_unbatched, observation_dim=2)
    horizon = registry.get("mse_chunk").horizon
    env = chunk_env(mm.TwoWayObstacleEnv(batch_size=(2,), seed=0))
    expert = mm.two_way_expert()
    buffer = DemonstrationBuffer()
    buffer.extend(rollout_episodes(env, as_actor(expert), 2, exploration=DET, max_steps=200))
    bc = BCConfig(num_steps=5, batch_size=64)
    out = dagger(
        EnvSource(env, exploration=None, max_steps=200),
        expert,
        lambda: build("mse_chunk", task, shared=dict(hidden=(16,))),
        buffer,
        DAggerConfig(rounds=2, episodes_per_round=2, bc=bc, seed=0),
        train=lambda learner, buf: fit_bc(learner, add_chunk_labels(buf.data, horizon), bc),
    )
    rows = out.buffer.data
    relabelled = rows[rows.get(keys.ROUND) == 1]
    assert not relabelled.get(keys.EXPERT_EXECUTED).any()  # beta = 0: the learner drove
    # every visited state carries the expert's action there (its intent rides in the rows)
    want = mm.expert_modes(relabelled.get(keys.OBSERVATION))
    label = relabelled.get(keys.EXPERT_ACTION)[:, 0]
    assert bool(((label == want[:, 0]) | (label == want[:, 1])).all())
    # the chunk of a relabelled row: the learner drove (beta = 0), so the label of the next
    # row answers another question (what the expert does from where the learner went):
    # entry 0 alone is the expert's, the rest repeat it and are masked
    chunked = add_chunk_labels(relabelled, horizon)
    assert bool(chunked.get(CHUNK_PAD)[:, 1:].all()) and not chunked.get(CHUNK_PAD)[:, 0].any()
    first = chunked.get(EXPERT_CHUNK)[:, 0]
    assert torch.equal(first, relabelled.get(keys.EXPERT_ACTION))
    assert torch.equal(
        chunked.get(EXPERT_CHUNK), first.unsqueeze(1).expand_as(chunked.get(EXPERT_CHUNK))
    )
    # the demonstrations (the expert drove) keep whole chunks: the next rows' labels
    demo = rows[rows.get(keys.ROUND) == 0]
    chunked = add_chunk_labels(demo, horizon)
    ep, st = demo.get(keys.EPISODE), demo.get(keys.STEP)
    for i in range(0, demo.shape[0], 7):
        for h in range(horizon):
            same = (ep == ep[i]) & (st == st[i] + h)
            pad = bool(chunked.get(CHUNK_PAD)[i, h])
            assert pad == (not bool(same.any()))
            if not pad:
                assert torch.equal(
                    chunked.get(EXPERT_CHUNK)[i, h], demo.get(keys.EXPERT_ACTION)[same][0]
                )


def test_a_chunk_ends_where_the_executed_action_was_not_the_experts():
    # one episode of 6 steps; the learner drove at steps 2 and 3 (beta mixing)
    label = torch.arange(6.0).unsqueeze(-1)
    executed = torch.tensor([True, True, False, False, True, True])
    chunk, pad = chunk_labels(
        label, torch.zeros(6, dtype=torch.long), torch.arange(6), 3, expert_executed=executed
    )
    # row 0: steps 0, 1, 2 on the expert's plan (actions 0 and 1 were its own)
    # row 1: steps 1, 2, then 3 was reached by the learner's action at 2: padded (2 repeated)
    # rows 2, 3: the learner acted at once: entry 0 only; rows 4, 5: the episode's end
    assert chunk[..., 0].tolist() == [
        [0, 1, 2],
        [1, 2, 2],
        [2, 2, 2],
        [3, 3, 3],
        [4, 5, 5],
        [5, 5, 5],
    ]
    assert pad.tolist() == [
        [False, False, False],
        [False, False, True],
        [False, True, True],
        [False, True, True],
        [False, False, True],
        [False, True, True],
    ]
    with pytest.raises(ValueError, match="expert_executed"):
        chunk_labels(label, torch.zeros(6, dtype=torch.long), torch.arange(6), 3,
                     expert_executed=executed[:5])  # fmt: skip

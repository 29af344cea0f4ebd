"""Chunks under inference latency (``DelayedChunkPolicy``, issue 48).

A stub network whose chunk from the observation ``o`` is ``o + i`` (``i`` the action's index
in the chunk), fed the step count as its observation, executes ``t`` at step ``t`` exactly
when each chunk is used at the right index: the schedules of every mode are checked against
hand-written sequences, and with no delay against ``ChunkedPolicy``'s own execution. The
guided samplers of real-time chunking: zero weights give the plain sample, weights pull the
sample to the target.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded

from imitrl import keys
from imitrl.data.chunks import IS_INIT
from imitrl.learners.diffusion.policy import DiffusionPolicy, ddim_sample, ddim_sample_guided
from imitrl.learners.flow.policy import FlowPolicy
from imitrl.policies.chunking import ChunkedPolicy, ChunkExecution, tile_spec
from imitrl.policies.latency import (
    CHUNK_SWITCH,
    DelayedChunkPolicy,
    Latency,
    hold_action,
    rtc_weights,
)

HOLD = -1.0


class _Clock(TensorDictModuleBase):
    """Flat chunk ``[B, H]`` (m = 1): entry ``i`` is ``scale * o + i``; records RTC's asks."""

    in_keys, out_keys = [keys.OBSERVATION], [keys.ACTION]

    def __init__(self, horizon: int, scale: float = 1.0) -> None:
        super().__init__()
        self.horizon, self.scale, self.asks = horizon, scale, []

    def forward(self, td):
        o = td.get(keys.OBSERVATION)[..., :1]
        td.set(keys.ACTION, self.scale * o + torch.arange(self.horizon, dtype=torch.float32))
        return td

    def inpaint(self, td, target, weights, guidance):
        self.asks.append((td.get(keys.OBSERVATION)[..., 0].clone(), target, weights, guidance))
        return self(td.clone()).get(keys.ACTION)


def _run(policy, steps: int, resets=(0,), lanes: int = 1, offset=(0,)) -> tuple[list, list]:
    """Actions and switches of lane 0 (and the others') over ``steps`` steps; a lane's
    observation is its steps since its last reset."""
    clock = torch.tensor(offset[:lanes] if len(offset) >= lanes else [0] * lanes).float()
    acts, switches = [], []
    for t in range(steps):
        init = torch.tensor([t in resets] * lanes)
        clock = torch.where(init, 0.0, clock)
        td = TensorDict(
            {keys.OBSERVATION: clock[:, None].repeat(1, 2), IS_INIT: init[:, None]}, [lanes]
        )
        out = policy(td)
        acts.append(out.get(keys.ACTION)[:, 0].tolist())
        switches.append(out.get(CHUNK_SWITCH).tolist())
        clock = clock + 1
    return acts, switches


def _policy(mode: str, d: int, s: int = 4, H: int = 8, **kw) -> DelayedChunkPolicy:
    hold = torch.tensor([HOLD]) if mode == "sync" else None
    return DelayedChunkPolicy(_Clock(H, **kw), 1, H, Latency(d, mode, execute=s), hold=hold)


@pytest.mark.parametrize("d", [0, 1, 2, 4])
def test_naive_async_executes_each_chunk_from_its_delay_on(d):
    acts, switches = _run(_policy("naive", d), 20)
    assert [a[0] for a in acts] == list(range(20))  # every chunk used at the right index
    # a new chunk takes over every s = 4 steps
    assert [t for t, s in enumerate(switches) if s[0]] == [0, 4, 8, 12, 16]


def test_naive_async_queries_d_steps_before_the_chunk_runs_out():
    network = _Clock(8, scale=10.0)  # the chunk says which observation it was planned from
    policy = DelayedChunkPolicy(network, 1, 8, Latency(3, "naive", execute=5))
    acts, _ = _run(policy, 12)
    # chunk 0 from o=0 at steps 0-4; chunk 1 queried at step 2 (o=2), used from its action 3
    assert [a[0] for a in acts] == [0, 1, 2, 3, 4, 23, 24, 25, 26, 27, 73, 74]


def test_sync_holds_still_while_it_waits_then_runs_the_chunk_from_its_start():
    acts, switches = _run(_policy("sync", 2), 16)
    expected = [0, 1, 2, 3, HOLD, HOLD, 4, 5, 6, 7, HOLD, HOLD, 10, 11, 12, 13]
    assert [a[0] for a in acts] == expected  # planned at steps 4 and 10, run from step 6, 12
    assert [t for t, s in enumerate(switches) if s[0]] == [0, 6, 12]


@pytest.mark.parametrize("mode", ["naive", "sync"])
def test_without_delay_it_is_the_receding_horizon(mode):
    network = _Clock(6, scale=3.0)
    plain = ChunkedPolicy(network, 1, ChunkExecution(6, execute=3))
    delayed = DelayedChunkPolicy.wrapping(plain, Latency(0, mode), hold=torch.tensor([HOLD]))
    resets = (0, 7, 8)
    assert _run(delayed, 20, resets)[0] == _run_plain(plain, 20, resets)


def _run_plain(policy, steps, resets):
    clock, acts = 0.0, []
    for t in range(steps):
        clock = 0.0 if t in resets else clock
        td = TensorDict(
            {keys.OBSERVATION: torch.full((1, 2), clock), IS_INIT: torch.tensor([[t in resets]])},
            [1],
        )
        acts.append(policy(td).get(keys.ACTION)[:, 0].tolist())
        clock += 1
    return acts


def test_without_delay_ensembling_is_acts():
    network = _Clock(5, scale=7.0)
    plain = ChunkedPolicy(network, 1, ChunkExecution(5, ensemble=0.3))
    delayed = DelayedChunkPolicy.wrapping(plain, Latency(0, "ensemble"))
    got, want = _run(delayed, 14, (0, 9))[0], _run_plain(plain, 14, (0, 9))
    assert torch.allclose(torch.tensor(got), torch.tensor(want), atol=1e-5)


def test_ensembling_averages_only_the_chunks_that_have_arrived():
    m, d, H = 0.2, 2, 5
    policy = DelayedChunkPolicy(_Clock(H, scale=10.0), 1, H, Latency(d, "ensemble", ensemble=m))
    acts, _ = _run(policy, 9)
    for t, (a,) in enumerate(acts):
        # chunk t' (planned from o = t') says 10 t' + (t - t') for step t; it has arrived
        # when t' <= t - d, or t' = 0 (the first chunk is ready at once); it lasts H steps
        ages = [t - q for q in range(t + 1) if t - q < H and (q <= t - d or q == 0)]
        w = torch.tensor([math.exp(m * j) for j in ages], dtype=torch.float64)
        pred = torch.tensor([10 * (t - j) + j for j in ages], dtype=torch.float64)
        assert a == pytest.approx(float((w * pred).sum() / w.sum()), rel=1e-6), t


@pytest.mark.parametrize("m", [7.0, 10.0, 40.0])
def test_ensembling_with_a_steep_m_keeps_finite_weights(m):
    """``m (H - 1)`` past about 103 underflowed every arrived weight against the oldest
    slot (0 / 0: NaN actions from the first step); the weights are the same, relative to
    the largest arrived one, and the plain policy's ensembling agrees."""
    H = 16
    delayed = DelayedChunkPolicy(_Clock(H, scale=10.0), 1, H, Latency(0, "ensemble", ensemble=m))
    plain = ChunkedPolicy(_Clock(H, scale=10.0), 1, ChunkExecution(H, ensemble=m))
    got, want = _run(delayed, 20)[0], _run_plain(plain, 20, (0,))
    assert all(math.isfinite(a) for (a,) in got)
    assert torch.allclose(torch.tensor(got), torch.tensor(want), atol=1e-4)


@pytest.mark.parametrize(
    "make",
    [
        lambda: ChunkExecution(4, ensemble=math.inf),
        lambda: ChunkExecution(4, ensemble=math.nan),
        lambda: ChunkExecution(4, execute=2.5),
        lambda: ChunkExecution(True),
        lambda: ChunkExecution(math.inf),
        lambda: Latency(math.inf, "naive"),
        lambda: Latency(1.5, "naive"),
        lambda: Latency(1, "naive", execute=True),
        lambda: Latency(1, "naive", execute=math.inf),
        lambda: Latency(0, "ensemble", ensemble=math.inf),
    ],
)
def test_chunk_settings_that_are_not_whole_or_finite_are_refused(make):
    """Each was taken (NaN actions, a replan every 3 steps for 2.5) or an OverflowError."""
    with pytest.raises(ValueError, match="must be"):
        make()


def test_rtc_inpaints_towards_what_the_current_chunk_still_holds():
    network = _Clock(8, scale=10.0)
    policy = DelayedChunkPolicy(network, 1, 8, Latency(2, "rtc", execute=4, guidance=3.0))
    acts, _ = _run(policy, 7)
    assert [a[0] for a in acts] == [0, 1, 2, 3, 22, 23, 24]  # naive's schedule
    obs, target, weights, guidance = network.asks[0]
    assert obs.tolist() == [2.0] and guidance == 3.0  # asked at step 2, chunk 0 ran 2 steps
    assert target[0].tolist() == [2, 3, 4, 5, 6, 7, 7, 7]  # chunk 0 from step 2 on, padded
    assert torch.equal(weights, rtc_weights(8, 2, torch.tensor([2])))


def test_rtc_weights_freeze_the_delay_and_decay_to_the_overlaps_end():
    w = rtc_weights(8, 2, torch.tensor([4, 2]))
    assert w[0, :2].tolist() == [1.0, 1.0] and w[0, 4:].tolist() == [0.0] * 4
    c = (8 - 4 - 2) / (8 - 4 - 2 + 1)
    assert w[0, 2].item() == pytest.approx(c * (math.exp(c) - 1) / (math.e - 1), rel=1e-6)
    assert (w[0, 2:4].diff() < 0).all() and w[1, 6:].eq(0).all() and (w[1, 2:6] > 0).all()
    # without a delay nothing is frozen, but the overlap is still pulled (so rtc at d = 0
    # is not the receding horizon, as the module says)
    w0 = rtc_weights(6, 0, torch.tensor([3]))[0]
    assert (w0[:3] > 0).all() and (w0[:3] < 1).all() and w0[3:].eq(0).all()


def test_lanes_reset_at_different_steps_each_keep_their_own_schedule():
    policy = _policy("naive", 2)
    both, _ = _run(policy, 12, resets=(0,), lanes=2, offset=(0, 0))
    assert [a[0] for a in both] == [a[1] for a in both] == list(range(12))


@pytest.mark.parametrize(
    "latency, hold, said",
    [
        (Latency(3, "naive", execute=2), None, "delay <= execute <= horizon - delay"),
        (Latency(5, "rtc", execute=4), None, "delay <= execute <= horizon - delay"),
        (Latency(1, "sync", execute=4), None, "give hold"),
        (Latency(8, "ensemble"), None, "delay < horizon 8"),
    ],
)
def test_what_a_mode_cannot_do_is_refused(latency, hold, said):
    with pytest.raises(ValueError, match=said):
        DelayedChunkPolicy(_Clock(8), 1, 8, latency, hold=hold)


def test_rtc_needs_a_network_that_can_be_guided():
    class Plain(_Clock):
        inpaint = None

    with pytest.raises(ValueError, match="guided sampler"):
        DelayedChunkPolicy(Plain(8), 1, 8, Latency(1, "rtc", execute=4))
    with pytest.raises(ValueError, match="mode must be one of"):
        Latency(1, "eager")


def test_hold_action_is_zero_moved_into_the_bounds():
    spec = Bounded(torch.tensor([-1.0, 0.5]), torch.tensor([1.0, 2.0]), shape=(2,))
    assert hold_action(spec).tolist() == [0.0, 0.5]


# --------------------------------------------------------------- guided samplers
def _flow() -> FlowPolicy:
    spec = tile_spec(Bounded(-torch.ones(1), torch.ones(1), shape=(1,)), 6)
    return FlowPolicy(3, spec, hidden=(16,), num_steps=6, normalize=False, seed=1)


def test_a_flow_guided_with_zero_weights_is_the_plain_sample():
    flow, obs = _flow(), torch.randn(4, 3, generator=torch.Generator().manual_seed(0))
    x0 = torch.randn(4, 6, generator=torch.Generator().manual_seed(1))
    zero = torch.zeros(4, 6)
    assert torch.equal(flow.sample_guided(obs, x0, zero, zero, 5.0), flow.sample(obs, x0))


def test_a_flow_guided_towards_a_target_ends_nearer_it_where_weighted():
    flow, obs = _flow(), torch.randn(64, 3, generator=torch.Generator().manual_seed(0))
    x0 = torch.randn(64, 6, generator=torch.Generator().manual_seed(1))
    target = torch.full((64, 6), 0.8)
    w = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]).expand(64, 6)
    plain = flow.sample(obs, x0)
    guided = flow.sample_guided(obs, x0, target, w, 5.0)
    near = lambda x: (x - target).abs()[:, :3].mean()  # noqa: E731
    assert near(guided) < 0.25 * near(plain)


def test_ddim_guided_with_zero_weights_is_ddim():
    policy = DiffusionPolicy(3, Bounded(-torch.ones(4), torch.ones(4), shape=(4,)), hidden=(16,),
                             num_steps=20, sampler="ddim", sample_steps=5, seed=2)  # fmt: skip
    obs = torch.randn(8, 3, generator=torch.Generator().manual_seed(0))
    x = torch.randn(8, 4, generator=torch.Generator().manual_seed(1))
    a = ddim_sample(policy._score, obs, x, policy._alphas_cumprod, 5)
    zero = torch.zeros(8, 4)
    b = ddim_sample_guided(policy._score, obs, x, policy._alphas_cumprod, 5, zero, zero, 5.0)
    assert torch.allclose(a, b, atol=1e-5)
    target = torch.full((8, 4), -0.7)
    c = ddim_sample_guided(policy._score, obs, x, policy._alphas_cumprod, 5, target,
                           torch.ones(8, 4), 5.0)  # fmt: skip
    assert (c - target).abs().mean() < 0.7 * (a - target).abs().mean()

"""GAIL and AIRL on the one rollout loop: fixed-step batches on N lanes, same digits.

``play_steps`` continues every lane across calls; the generator's batches come from the
seam's stepper, the accelerated one and TorchRL's reference giving the same numbers; a
run depends on (seed, lanes) only.
"""

from __future__ import annotations

import contextlib

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.algorithms.adversarial import AIRLConfig, GAILConfig, airl, gail
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.experts import cartpole_expert, pendulum_expert
from imitrl.jobs.configs import GAILJob
from imitrl.learners import build
from imitrl.runtime import paths, rollout_episodes
from imitrl.runtime.fast import gae_step
from imitrl.runtime.fast.gae_step import DistinctRows
from imitrl.runtime.loop import STEP_ROW_KEYS, play_steps

TINY = dict(total_steps=256, rollout_steps=128, ppo_epochs=2, minibatch_size=64,
            discriminator_updates=2, discriminator_batch=32)  # fmt: skip


def _setup(env_id: str, lanes: int, seed: int = 0):
    env = make_env(env_id, seed=seed, num_envs=lanes)
    demo = make_env(env_id, seed=seed)
    expert = cartpole_expert() if env_id == "CartPole-v1" else pendulum_expert()
    buffer = DemonstrationBuffer(action_spec=demo.action_spec_unbatched)
    buffer.extend(rollout_episodes(demo, expert, 1))
    head = "categorical" if env_id == "CartPole-v1" else "tanh_normal"
    return env, buffer, build("for_env", demo, head=head, hidden=(16,), seed=seed, value=True)


def _run(method: str, env_id: str, lanes: int):
    env, buffer, learner = _setup(env_id, lanes)
    if method == "gail":
        result = gail(env, learner, buffer, GAILConfig(**TINY))
    else:
        result, _ = airl(env, learner, buffer, AIRLConfig(**TINY))
    return [(r.discriminator, r.generator, r.learned_reward) for r in result.rounds], learner


def _same_weights(a, b) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


@pytest.mark.parametrize(("method", "env_id"), [("gail", "CartPole-v1"), ("airl", "Pendulum-v1")])
@pytest.mark.parametrize("lanes", [1, 4])
def test_a_run_depends_on_seed_and_lanes_and_both_paths_agree(method, env_id, lanes):
    first, la = _run(method, env_id, lanes)
    again, lb = _run(method, env_id, lanes)
    assert first == again and _same_weights(la, lb)
    with paths.reference():  # TorchRL's step_and_maybe_reset, the actor's own forward
        slow, lc = _run(method, env_id, lanes)
    assert first == slow and _same_weights(la, lc)


def test_the_generator_takes_the_tensor_ppo_step_where_it_computes_the_same():
    """The test above compares the paths only if the fast one runs: it does for every
    probabilistic head at imitrl's settings, and not with an entropy bonus (whose Monte
    Carlo estimate for a tanh-normal draws from the RNG): there the loss module runs."""
    from imitrl.algorithms.adversarial.generator import PPOGenerator

    kw = dict(gamma=0.99, gae_lambda=0.95, clip_epsilon=0.2, epochs=1, minibatch_size=8,
              max_grad_norm=0.5)  # fmt: skip
    for env_id in ("CartPole-v1", "Pendulum-v1"):
        _, _, learner = _setup(env_id, 1)
        assert paths.ppo_loss(PPOGenerator(learner, entropy_coeff=0.0, **kw).loss).accelerated
        assert not paths.ppo_loss(PPOGenerator(learner, entropy_coeff=0.01, **kw).loss).accelerated
        with paths.reference():
            plain = PPOGenerator(learner, entropy_coeff=0.0, **kw).loss
            assert not paths.ppo_loss(plain).accelerated
        # a batch with an entry ClipPPOLoss reads as a loss mask: the module itself
        masked = TensorDict({"shifted_valid": torch.ones(4, dtype=torch.bool)}, [4])
        loss = PPOGenerator(learner, entropy_coeff=0.0, **kw).loss
        assert not paths.ppo_loss(loss, masked).accelerated
        assert not paths.ppo_loss(loss, masked[:0]).accelerated
        assert paths.ppo_loss(loss, TensorDict({}, [4])).accelerated


def test_other_lane_counts_play_other_episodes():
    one, _ = _run("gail", "CartPole-v1", 1)
    four, _ = _run("gail", "CartPole-v1", 4)
    assert one != four  # lane i is seeded seed + i: another sample, the same protocol


@pytest.mark.parametrize("fast", [True, False])
def test_play_steps_continues_every_lane_across_calls(fast):
    """Two calls of 5 steps are one call of 10 steps, cut in two: each lane goes on from
    where it was, episodes crossing the cut; ``("next", "observation")`` is each step's
    own (before a reset), the next row's observation unless the lane ended there."""

    def batches(sizes):
        env = make_env("CartPole-v1", seed=3, num_envs=3, max_episode_steps=4)
        learner = build("for_env", env, hidden=(8,), seed=0, value=True)
        torch.manual_seed(0)
        path = contextlib.nullcontext() if fast else paths.reference("stepper")
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad(), path:
            stepper = paths.stepper(env, learner.policy, record=True, row_keys=STEP_ROW_KEYS,
                                    next_observation=True)  # fmt: skip
            stepper.reset()
            return [play_steps(stepper, n) for n in sizes]

    (whole,), parts = batches([10]), batches([5, 5])
    assert whole.shape == (3, 10) and [p.shape for p in parts] == [(3, 5), (3, 5)]
    joined = torch.cat(parts, dim=1)
    for key in whole.keys(True, True):
        assert torch.equal(whole[key], joined[key]), key
    done = whole[keys.NEXT, keys.DONE].squeeze(-1)
    assert bool(done[:, 3].all())  # the time limit of 4 ends every lane's first episode
    nxt, obs = whole[keys.NEXT, keys.OBSERVATION], whole[keys.OBSERVATION]
    cont = ~done[:, :-1]
    assert torch.equal(nxt[:, :-1][cont], obs[:, 1:][cont])
    assert not torch.equal(nxt[:, 3], obs[:, 4])  # the lanes reset after step 3


def test_round_sizes_must_split_over_the_lanes():
    env, buffer, learner = _setup("CartPole-v1", 3)
    with pytest.raises(ValueError, match="multiple of the env's 3 lanes"):
        gail(env, learner, buffer, GAILConfig(**TINY))
    with pytest.raises(ValueError, match=r"--rollout-steps .* multiple of --num-envs"):
        GAILJob(num_envs=3)
    with pytest.raises(ValueError, match="--num-envs must be an integer >= 1"):
        GAILJob(num_envs=0)
    assert GAILConfig().total_steps % GAILConfig().rollout_steps == 0  # whole rounds


def test_the_gail_job_runs_on_lanes(tmp_path):
    from imitrl.jobs.gail import run_gail

    config = GAILJob(num_envs=4, max_episode_steps=50, eval_episodes=2, eval_every=0,
                     out=tmp_path, progress=False, **TINY)  # fmt: skip
    results = run_gail(config)
    assert results["env_steps"] == 256 and len(results["rounds"]) == 2


def _round_batch(env_id: str, lanes: int) -> TensorDict:
    """One round's batch as the generator sees it, with a learned reward."""
    env, _, learner = _setup(env_id, lanes)
    stepper = paths.stepper(env, learner.policy, record=True, row_keys=STEP_ROW_KEYS,
                            next_observation=True)  # fmt: skip
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        stepper.reset()
        batch = play_steps(stepper, 64)
    reward = torch.randn(*batch.shape, 1, generator=torch.Generator().manual_seed(1))
    batch.set(("next", "learned_reward"), reward)
    return batch, learner


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
@pytest.mark.parametrize("lanes", [1, 3])
@pytest.mark.parametrize("vectorized", [None, True])
def test_gae_on_tensors_writes_the_modules_bits(env_id, lanes, vectorized):
    from torchrl.objectives.value import GAE

    batch, learner = _round_batch(env_id, lanes)
    module = GAE(gamma=0.97, lmbda=0.9, value_network=learner.value, vectorized=vectorized)
    module.set_keys(reward="learned_reward")
    fast = paths.gae(module, batch)
    assert fast is not module
    ref, out = batch.clone(), batch.clone()
    with torch.no_grad():
        module(ref)
    fast(out)
    for key in ("advantage", "value_target", "state_value", ("next", "state_value")):
        assert torch.equal(out.get(key), ref.get(key)), key
    with paths.reference():
        assert paths.gae(module, batch) is module


def test_gae_on_tensors_steps_aside_where_the_module_computes_otherwise():
    from torchrl.objectives.value import GAE

    batch, learner = _round_batch("Pendulum-v1", 2)
    module = GAE(gamma=0.97, lmbda=0.9, value_network=learner.value)
    module.set_keys(reward="learned_reward")
    for other in (
        GAE(gamma=0.97, lmbda=0.9, value_network=learner.value, average_gae=True),
        GAE(gamma=0.97, lmbda=0.9, value_network=learner.value, shifted=True),
        GAE(gamma=0.97, lmbda=0.9, value_network=learner.value, value_chunk_size=16),
    ):
        assert paths.gae(other, batch) is other
    steps = batch.clone().set("steps_to_next_obs", torch.ones(*batch.shape, 1))
    assert paths.gae(module, steps) is module
    # a NaN next observation (a compact-observation collector's episode end): the module
    # substitutes the observation; the fast path hands such a batch to it
    holed = batch.clone()
    holed.get(("next", "observation"))[0, 3] = float("nan")
    ref = holed.clone()
    with torch.no_grad():
        module(ref)
    out = paths.gae(module, holed)(holed)
    assert torch.equal(out.get("advantage"), ref.get("advantage"))
    assert not torch.isnan(out.get("advantage")).any()


@pytest.mark.parametrize("shape", [(50, 1), (3, 40, 1), (2, 2, 30, 2)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_recursion_over_numpy_gives_torchrls_gae_bits(shape, dtype):
    from torchrl.objectives.value.functional import generalized_advantage_estimate

    from imitrl.runtime.fast.gae_step import recursive_gae

    g = torch.Generator().manual_seed(len(shape))
    v, nv, r = (torch.randn(shape, generator=g, dtype=dtype) * 10 for _ in range(3))
    done = torch.rand(shape, generator=g) < 0.1
    terminated = done & (torch.rand(shape, generator=g) < 0.5)
    gamma, lmbda = torch.tensor(0.99, dtype=dtype), torch.tensor(0.95, dtype=dtype)
    ref = generalized_advantage_estimate(gamma, lmbda, v, nv, r, done, terminated)
    out = recursive_gae(gamma, lmbda, v, nv, r, done=done, terminated=terminated)
    for a, b in zip(out, ref):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)


def test_gae_on_tensors_refuses_value_modules_and_modes_it_does_not_replay():
    from tensordict.nn import TensorDictModule, TensorDictSequential, set_skip_existing
    from torchrl.objectives.value import GAE

    batch, learner = _round_batch("Pendulum-v1", 2)
    net = learner.value.module
    seq = TensorDictSequential(
        TensorDictModule(net, in_keys=["observation"], out_keys=["state_value"]),
        selected_out_keys=["state_value"],
    )
    for value, skip in ((seq, None), (learner.value, True)):
        module = GAE(gamma=0.97, lmbda=0.9, value_network=value, skip_existing=skip)
        module.set_keys(reward="learned_reward")
        assert paths.gae(module, batch) is module
    module = GAE(gamma=0.97, lmbda=0.9, value_network=learner.value)
    module.set_keys(reward="learned_reward")
    with set_skip_existing(True):
        assert paths.gae(module, batch) is module
    # a float64 reward beside float32 values: the function itself (it rounds each step)
    wide = batch.clone()
    wide.set(("next", "learned_reward"), wide.get(("next", "learned_reward")).double() / 3)
    ref = wide.clone()
    with torch.no_grad():
        module(ref)
    out = paths.gae(module, wide)(wide.clone())
    assert torch.equal(out.get("advantage"), ref.get("advantage"))


# GAE's value network on each observation once (runtime.fast.gae_step.DistinctRows):
# within a lane, a step's next observation is the following step's unless an episode
# ended; the distinct call runs only where it gave the stacked call's bits
def _rowwise(x: torch.Tensor) -> torch.Tensor:
    """A row's value from that row alone: ``[N, F] -> [N, 1]``."""
    return (x * torch.arange(1, x.shape[-1] + 1, dtype=x.dtype)).sum(-1, keepdim=True)


def test_distinct_rows_give_back_both_ends_of_every_step():
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(3, 10, 2, generator=g)
    nxt = torch.cat([obs[:, 1:], torch.randn(3, 1, 2, generator=g)], 1).clone()
    nxt[0, 4] = torch.randn(2, generator=g)  # an episode's end: a reset follows
    nxt[2, 7] = torch.randn(2, generator=g)
    obs[1, 3, 0], nxt[1, 2, 0] = 0.0, -0.0  # equal as numbers, not as bits
    rows = DistinctRows.of(obs, nxt, batch_dims=2, time_dim=1)
    extra = 3 + 3  # each lane's last step, two resets and the signed zero
    assert rows.n_extra == extra
    assert rows.inputs.shape == (64, 2)  # 30 + 6 rows, padded to a block
    value, next_value = rows.values(_rowwise(rows.inputs))
    assert torch.equal(value, _rowwise(obs.reshape(-1, 2)).reshape(3, 10, 1))
    assert torch.equal(next_value, _rowwise(nxt.reshape(-1, 2)).reshape(3, 10, 1))
    assert torch.signbit(rows.inputs[30:36]).any()  # the -0.0 row is its own
    # not a [*B, T, F] batch with time last: the stacked call
    assert DistinctRows.of(obs, nxt, batch_dims=2, time_dim=0) is None
    assert DistinctRows.of(obs[..., None], nxt[..., None], batch_dims=2, time_dim=1) is None
    assert DistinctRows.of(obs[:, :1], nxt[:, :1], batch_dims=2, time_dim=1) is None


def _gae_and_calls(batch, learner):
    from torchrl.objectives.value import GAE

    module = GAE(gamma=0.97, lmbda=0.9, value_network=learner.value)
    module.set_keys(reward="learned_reward")
    fast = paths.gae(module, batch)
    calls = []
    net = fast.net
    fast.net = lambda x: calls.append(x[..., 0].numel()) or net(x)
    return module, fast, calls


def test_the_distinct_call_runs_after_agreeing_once_and_gives_the_modules_bits(monkeypatch):
    monkeypatch.setattr(gae_step, "_DISTINCT_AGREES", {})
    batch, learner = _round_batch("CartPole-v1", 3)  # episodes end inside the batch
    module, fast, calls = _gae_and_calls(batch, learner)
    ref = batch.clone()
    with torch.no_grad():
        module(ref)
    n = batch.numel()
    for _ in range(3):
        out = fast(batch.clone())
        for key in ("advantage", "value_target", "state_value", ("next", "state_value")):
            assert torch.equal(out.get(key), ref.get(key)), key
    assert list(gae_step._DISTINCT_AGREES.values()) == [True]
    # the first call: the stacked one and the distinct one compared; then distinct only
    distinct = -(-(n + 3) // 64) * 64
    assert calls[0] == 2 * n and calls[1] >= distinct and calls[2:] == [calls[1]] * 2
    assert calls[1] < 2 * n


def test_a_signature_whose_calls_disagreed_keeps_the_stacked_call(monkeypatch):
    batch, learner = _round_batch("Pendulum-v1", 2)
    module, fast, calls = _gae_and_calls(batch, learner)
    rows = DistinctRows.of(
        batch.get("observation"), batch.get(("next", "observation")), batch.ndim, batch.ndim - 1
    )
    monkeypatch.setattr(gae_step, "_DISTINCT_AGREES", {rows.signature(fast.params): False})
    ref = batch.clone()
    with torch.no_grad():
        module(ref)
    for _ in range(2):
        assert torch.equal(fast(batch.clone()).get("advantage"), ref.get("advantage"))
    assert calls == [2 * batch.numel()] * 2

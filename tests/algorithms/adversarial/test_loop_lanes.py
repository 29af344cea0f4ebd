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

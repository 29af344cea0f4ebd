"""Pixel learners, pixel envs and privileged-expert DAgger (issue 14, learner side)."""

from __future__ import annotations

import importlib.util

import pytest
import torch
from torchrl.data import Bounded
from torchrl.envs import CatFrames, TransformedEnv
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms.bc import BCConfig, fit_bc
from imitrl.algorithms.dagger import DAggerConfig, EnvSource, dagger
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.data.rollout import rollout_episodes
from imitrl.envs.multimodal import TwoWayObstacleEnv
from imitrl.envs.pixel_tasks import PixelTwoWayEnv, state_expert
from imitrl.evaluation.evaluate import evaluate
from imitrl.policies import ActorCritic
from imitrl.policies.encoders import PixelEncoder

ACTION = Bounded(-1.0, 1.0, shape=(1,), dtype=torch.float32)
SMALL = {"channels": (8, 8), "hidden": (32,)}  # fast on 2 CPU cores


def _images(n: int, shape=(16, 16, 3), seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, *shape), generator=g, dtype=torch.uint8)


def _demos(env, episodes: int = 2, seed: int = 0):
    return rollout_episodes(env, state_expert(), episodes, max_steps=60, seed=seed)


def test_cnn_learner_shapes_and_uint8_scaling():
    learner = ActorCritic.pixels((16, 16, 3), ACTION, **SMALL)
    assert learner.policy.in_keys == [keys.PIXELS]
    assert keys.PIXELS in learner.loss.in_keys  # fit_bc's rows carry the images
    action = learner.act_greedy(_images(5))
    assert action.shape == (5, 1) and bool((action.abs() <= 1).all())
    assert learner.values(_images(4)).shape == (4,)
    assert learner.act_greedy(_images(1)[0]).shape == (1,)  # unbatched image
    encoder = PixelEncoder((16, 16, 3), channels=(4,))
    full = torch.full((2, 16, 16, 3), 255, dtype=torch.uint8)
    with torch.no_grad():  # uint8 255 reaches the convolutions as 1.0, channels first
        assert torch.allclose(encoder(full), encoder.conv(torch.ones(2, 3, 16, 16)))
    with pytest.raises(ValueError, match="uint8"):
        encoder(full.float())
    with pytest.raises(ValueError, match=r"uint8 pixels \[\.\.\., 16, 16, 3\]"):
        learner.act_greedy(_images(2, shape=(16, 16, 4)))


def test_default_convolutions_fit_small_and_nature_sized_images():
    small = PixelEncoder((32, 32, 3))  # kernel 3, stride 2: 32 -> 16 -> 8 -> 4
    assert small.out_features == 64 * 4 * 4
    nature = PixelEncoder((84, 84, 3))  # 8/4, 4/2, 3/1: 84 -> 20 -> 9 -> 7
    assert nature.out_features == 64 * 7 * 7
    with pytest.raises(ValueError, match="too small"):
        PixelEncoder((4, 4, 3), kernels=(3, 3, 3), strides=(1, 1, 1), paddings=(0, 0, 0))


def test_frame_stacking_reads_frames_on_the_channel_axis():
    learner = ActorCritic.pixels((16, 16, 3), ACTION, frames=4, **SMALL)
    assert learner.pixel_shape == (16, 16, 12)
    assert learner.act_greedy(_images(3, shape=(16, 16, 12))).shape == (3, 1)
    env = TransformedEnv(
        PixelTwoWayEnv(pixels=(16, 16), seed=0),
        CatFrames(N=2, dim=-1, in_keys=[keys.PIXELS]),
    )
    stacked = ActorCritic.for_env(env, **SMALL)
    assert stacked.pixel_shape == (16, 16, 6)
    rows = rollout_episodes(env, state_expert(), 1, max_steps=60, seed=0)
    assert rows.get(keys.PIXELS).shape[1:] == (16, 16, 6)
    assert fit_bc(stacked, rows, BCConfig(num_steps=2)).num_rows == rows.shape[0]


def test_pixel_learner_with_state_reads_both_and_normalises_the_state():
    env = PixelTwoWayEnv(pixels=(16, 16), seed=0)
    learner = ActorCritic.for_env(env, state=True, **SMALL)
    assert learner.policy.in_keys == [keys.PIXELS, keys.OBSERVATION]
    assert learner.observation_shape == (2,) and learner.normalizer is not None
    rows = _demos(env)
    fit_bc(learner, rows, BCConfig(num_steps=2))
    obs = rows.get(keys.OBSERVATION)
    assert torch.allclose(learner.normalizer.loc, obs.mean(0))
    inputs = {keys.PIXELS: rows.get(keys.PIXELS)[:3], keys.OBSERVATION: obs[:3]}
    assert learner.act_greedy(inputs).shape == (3, 1)
    with pytest.raises(ValueError, match="reads the state"):
        learner.act_greedy({keys.PIXELS: rows.get(keys.PIXELS)[:3]})
    pixels_only = ActorCritic.for_env(env, **SMALL)  # the state stays the expert's
    assert pixels_only.policy.in_keys == [keys.PIXELS] and pixels_only.normalizer is None


def test_fit_bc_on_pixel_rows_reduces_the_loss():
    env = PixelTwoWayEnv(pixels=(16, 16), seed=0)
    rows = _demos(env)
    assert rows.get(keys.PIXELS).dtype == torch.uint8
    learner = ActorCritic.pixels((16, 16, 3), ACTION, lr=3e-3, **SMALL)
    result = fit_bc(learner, rows, BCConfig(num_steps=60))
    assert result.final_loss < 0.5 * float(result.losses[0])


def test_privileged_expert_dagger_runs_end_to_end_with_both_keys(tmp_path):
    env = PixelTwoWayEnv(pixels=(16, 16), batch_size=(2,), seed=0)
    expert = state_expert()
    assert expert.in_keys == [keys.OBSERVATION]  # labels from the state alone
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(_demos(env, episodes=1))
    result = dagger(
        EnvSource(env, max_steps=60),
        expert,
        lambda: ActorCritic.for_env(env, **SMALL),
        buffer,
        DAggerConfig(rounds=2, episodes_per_round=2, bc=BCConfig(num_steps=5)),
    )
    assert result.learner.policy.in_keys == [keys.PIXELS]
    data = result.buffer.data
    assert set(result.buffer.rounds()) == {0, 1}
    assert data.get(keys.PIXELS).shape[1:] == (16, 16, 3)
    assert data.get(keys.PIXELS).dtype == torch.uint8
    assert data.get(keys.OBSERVATION).shape[1:] == (2,)
    relabelled = data[data.get(keys.ROUND) == 1]
    labels = expert(relabelled.select(keys.OBSERVATION).clone()).get(keys.EXPERT_ACTION)
    assert torch.equal(relabelled.get(keys.EXPERT_ACTION), labels)
    ev = evaluate(env, result.learner, 2, max_steps=60, seed=1)
    assert ev.num_episodes == 2 and ev.exploration == "deterministic"
    loaded, _ = DemonstrationBuffer.load(buffer.save(tmp_path / "buf"))
    assert torch.equal(loaded.data.get(keys.PIXELS), data.get(keys.PIXELS))


def test_pixel_learner_on_an_env_without_pixels_is_refused_naming_both():
    learner = ActorCritic.pixels((16, 16, 3), ACTION, **SMALL)
    env = TwoWayObstacleEnv(seed=0)
    with pytest.raises(ValueError, match=r"reads uint8 'pixels' \[16, 16, 3\].*no 'pixels'"):
        evaluate(env, learner, 1, max_steps=60)
    other = PixelTwoWayEnv(pixels=(8, 8), seed=0)
    with pytest.raises(ValueError, match=r"\[16, 16, 3\].*gives 'pixels' torch.uint8 \[8, 8, 3\]"):
        learner.check_env(other)


def test_float_pixel_specs_are_refused():
    float_pixels = Bounded(0.0, 1.0, shape=(3, 16, 16), dtype=torch.float32)
    with pytest.raises(ValueError, match="uint8"):
        ActorCritic.pixels(float_pixels, ACTION)


@pytest.mark.skipif(importlib.util.find_spec("pygame") is None, reason="needs pygame")
def test_make_env_renders_cartpole_as_uint8_hwc():
    from imitrl.envs import make_env

    env = make_env("CartPole-v1", seed=0, pixels=(24, 36))
    spec = env.observation_spec_unbatched
    assert spec[keys.PIXELS].shape == (24, 36, 3) and spec[keys.PIXELS].dtype == torch.uint8
    assert spec[keys.OBSERVATION].shape == (4,)
    learner = ActorCritic.for_env(env, **SMALL)
    assert learner.pixel_shape == (24, 36, 3)
    summary = evaluate(env, learner, 1, exploration=ExplorationType.DETERMINISTIC)
    assert summary.mean_length >= 1
    rows = env.rollout(3)
    assert rows.get(keys.PIXELS).shape == (3, 24, 36, 3)
    assert rows.get(keys.PIXELS).dtype == torch.uint8
    env.close()

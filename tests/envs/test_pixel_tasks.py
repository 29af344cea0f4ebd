"""Pixel learners, pixel envs and privileged-expert DAgger (issue 14, learner side)."""

from __future__ import annotations

import importlib.util

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs import CatFrames, TransformedEnv
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms.bc import BCConfig, fit_bc
from imitrl.algorithms.dagger import DAggerConfig, EnvSource, dagger
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.envs.multimodal import TwoWayObstacleEnv
from imitrl.envs.pixel_tasks import (
    Hilltop,
    PixelBalanceEnv,
    PixelTwoWayEnv,
    balance_expert,
    state_expert,
)
from imitrl.evaluation.evaluate import evaluate
from imitrl.learners import ActorCritic, Learner, TaskSpec, build
from imitrl.policies.encoders import PixelEncoder
from imitrl.runtime.rollout import rollout_episodes

ACTION = Bounded(-1.0, 1.0, shape=(1,), dtype=torch.float32)
SMALL = {"channels": (8, 8), "hidden": (32,)}  # fast on 2 CPU cores


def _images(n: int, shape=(16, 16, 3), seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, *shape), generator=g, dtype=torch.uint8)


def _demos(env, episodes: int = 2, seed: int = 0):
    return rollout_episodes(env, state_expert(), episodes, max_steps=60, seed=seed)


def test_cnn_learner_shapes_and_uint8_scaling():
    learner = ActorCritic.pixels((16, 16, 3), ACTION, value=True, **SMALL)
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
    small = PixelEncoder(
        (32, 32, 3), channels=(32, 64, 64)
    )  # kernel 3, stride 2: 32 -> 16 -> 8 -> 4
    assert small.out_features == 64 * 4 * 4
    nature = PixelEncoder((84, 84, 3), channels=(32, 64, 64))  # 8/4, 4/2, 3/1: 84 -> 20 -> 9 -> 7
    assert nature.out_features == 64 * 7 * 7
    with pytest.raises(ValueError, match="too small"):
        PixelEncoder(
            (4, 4, 3), channels=(32, 64, 64), kernels=(3, 3, 3), strides=(1, 1, 1),
            paddings=(0, 0, 0),
        )  # fmt: skip


def test_frame_stacking_reads_frames_on_the_channel_axis():
    learner = ActorCritic.pixels((16, 16, 3), ACTION, frames=4, **SMALL)
    assert learner.pixel_shape == (16, 16, 12)
    assert learner.act_greedy(_images(3, shape=(16, 16, 12))).shape == (3, 1)
    env = TransformedEnv(
        PixelTwoWayEnv(pixels=(16, 16), seed=0),
        CatFrames(N=2, dim=-1, in_keys=[keys.PIXELS]),
    )
    stacked = build("for_env", env, **SMALL)
    assert stacked.pixel_shape == (16, 16, 6)
    rows = rollout_episodes(env, state_expert(), 1, max_steps=60, seed=0)
    assert rows.get(keys.PIXELS).shape[1:] == (16, 16, 6)
    assert fit_bc(stacked, rows, BCConfig(num_steps=2)).num_rows == rows.shape[0]


def test_pixel_learner_with_state_reads_both_and_normalises_the_state():
    env = PixelTwoWayEnv(pixels=(16, 16), seed=0)
    learner = build("for_env", env, state=True, **SMALL)
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
    pixels_only = build("for_env", env, **SMALL)  # the state stays the expert's
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
        lambda: build("for_env", env, **SMALL),
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
    learner = build("for_env", env, **SMALL)
    assert learner.pixel_shape == (24, 36, 3)
    summary = evaluate(env, learner, 1, exploration=ExplorationType.DETERMINISTIC)
    assert summary.mean_length >= 1
    rows = env.rollout(3)
    assert rows.get(keys.PIXELS).shape == (3, 24, 36, 3)
    assert rows.get(keys.PIXELS).dtype == torch.uint8
    env.close()


# ------------------------------------------------------------------ the hilltop task
def test_balance_env_draws_the_ball_where_the_state_is_and_replays_under_a_seed():
    env = PixelBalanceEnv(pixels=(16, 16), batch_size=(3,), seed=0)
    spec = env.observation_spec_unbatched
    assert spec[keys.PIXELS].shape == (16, 16, 3) and spec[keys.PIXELS].dtype == torch.uint8
    rows = rollout_episodes(env, balance_expert(), 3, max_steps=100, seed=5)
    pixels, obs = rows.get(keys.PIXELS), rows.get(keys.OBSERVATION)
    assert pixels.dtype == torch.uint8 and pixels.shape == (rows.shape[0], 16, 16, 3)
    # the green blob's centroid is the ball's position (view [-1, 1]^2, +y up)
    green = pixels[..., 1].double()  # [N, 16, 16]
    centres = (torch.arange(16, dtype=torch.float64) + 0.5) / 16 * 2 - 1
    mass = green.sum((-2, -1))
    x = (green.sum(-2) * centres).sum(-1) / mass
    y = (green.sum(-1) * -centres).sum(-1) / mass
    assert torch.allclose(torch.stack([x, y], -1).float(), obs, atol=0.02)
    again = rollout_episodes(env, balance_expert(), 3, max_steps=100, seed=5)
    assert torch.equal(again.get(keys.PIXELS), pixels)
    other = rollout_episodes(env, balance_expert(), 3, max_steps=100, seed=6)
    assert not torch.equal(other.get(keys.OBSERVATION)[:3], obs[:3])


def test_balance_expert_is_lipschitz_and_holds_the_ball_where_random_actions_drop_it():
    net = balance_expert(gain=8.0).module  # the expert's obs -> action map
    g = torch.Generator().manual_seed(0)
    p, q = torch.rand(2, 1000, 2, generator=g) - 0.5
    gap = (net(p) - net(q)).abs().amax(-1)
    assert bool((gap <= 8.0 * (p - q).abs().amax(-1) + 1e-6).all())  # no jump anywhere
    env = PixelBalanceEnv(pixels=(8, 8), batch_size=(20,), seed=0)
    expert = evaluate(env, balance_expert(), 20, max_steps=100, seed=1)
    assert expert.mean_return == Hilltop().horizon  # the most: every episode, every step
    random = Bounded(-1.0, 1.0, shape=(20, 2), dtype=torch.float32)
    env.set_seed(1)
    rows = env.rollout(100, policy=lambda td: td.set(keys.ACTION, random.rand()))
    assert float(rows.get(("next", keys.REWARD)).sum(-2).mean()) < 0.5 * Hilltop().horizon
    with pytest.raises(ValueError, match="gain must exceed the instability"):
        balance_expert(gain=1.0)
    with pytest.raises(ValueError, match="start"):
        Hilltop(start=0.6)


# ------------------------------------------------------------- pixel keys, cameras
TOP = ("pixels", "top")


def test_a_nested_camera_key_is_read_by_the_policy_the_value_and_the_loss():
    learner = ActorCritic.pixels((16, 16, 3), ACTION, pixel_key=TOP, value=True, **SMALL)
    assert learner.pixel_key == TOP and learner.policy.in_keys == [TOP]
    assert TOP in learner.loss.in_keys and keys.PIXELS not in learner.loss.in_keys
    images = _images(4)
    as_td = TensorDict({"pixels": {"top": images, "side": _images(4, seed=1)}}, [4])
    action = learner.act_greedy(as_td)
    assert action.shape == (4, 1)
    assert torch.equal(learner.act_greedy({"pixels": {"top": images}}), action)  # dict of dicts
    assert torch.equal(learner.act_greedy({TOP: images}), action)  # keyed by the tuple
    assert learner.values(as_td).shape == (4,)
    with pytest.raises(ValueError, match=r"lack \('pixels', 'top'\)"):
        learner.act_greedy(TensorDict({"pixels": {"side": images}}, [4]))
    rows = TensorDict(
        {"pixels": {"top": images}, keys.EXPERT_ACTION: torch.zeros(4, 1)},
        [4],
    )
    rows.set(keys.OBSERVATION, torch.zeros(4, 2))  # fit_bc's rows keep the state today
    assert fit_bc(learner, rows, BCConfig(num_steps=2)).num_rows == 4
    with pytest.raises(ValueError, match="pixel_key must be"):
        ActorCritic.pixels((16, 16, 3), ACTION, pixel_key=("pixels", ""))
    with pytest.raises(ValueError, match="lies under 'observation'"):
        ActorCritic.pixels((16, 16, 3), ACTION, state=2, pixel_key=("observation", "cam"))


def test_a_camera_key_the_env_lacks_is_refused_naming_it():
    env = PixelBalanceEnv(pixels=(16, 16), seed=0)
    learner = ActorCritic.pixels((16, 16, 3), Bounded(-1.0, 1.0, shape=(2,)), pixel_key=TOP)
    with pytest.raises(ValueError, match=r"no \('pixels', 'top'\) observation"):
        learner.check_env(env)
    with pytest.raises(ValueError, match=r"reads \[\('pixels', 'top'\)\]"):
        build("for_env", env, pixel_key=TOP)
    assert build("for_env", env, pixel_key=keys.PIXELS, **SMALL).pixel_key == keys.PIXELS


def test_camera_only_rows_pass_prepare_when_the_state_is_not_read():
    rows = TensorDict({keys.PIXELS: _images(6), keys.EXPERT_ACTION: torch.zeros(6, 1)}, [6])
    images_only = ActorCritic.pixels((16, 16, 3), ACTION, **SMALL)
    images_only.prepare(rows)  # no OBSERVATION anywhere: fine
    images_only.check_observations(rows)
    with_state = ActorCritic.pixels((16, 16, 3), ACTION, state=2, **SMALL)
    with pytest.raises(ValueError, match="reads the state 'observation'"):
        with_state.prepare(rows)
    mlp = build("for_env", TaskSpec.from_specs(2, ACTION), hidden=(8,))
    with pytest.raises(ValueError, match="rows lack 'observation', which the policy reads"):
        mlp.prepare(rows)
    # the base contract too: a user's Learner of images alone takes camera-only rows
    plain = Learner(images_only.policy, images_only.loss, images_only.opt_pi)
    plain.prepare(rows)

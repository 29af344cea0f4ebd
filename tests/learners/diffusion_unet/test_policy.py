"""Diffusion Policy as a learner (issue 30): the registry's ``diffusion_unet``, observation
histories fed at act time as the rows carry them, EMA weights through fits and
checkpoints, the warm-up and cosine schedule, the masked epsilon loss."""

from __future__ import annotations

import copy
import math
from dataclasses import replace

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.algorithms.bc import _Cosine
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK, IS_INIT
from imitrl.data.history import OBS_HISTORY, add_observation_history
from imitrl.learners import build, registry
from imitrl.learners.diffusion_unet import UnetDiffusionConfig
from imitrl.learners.task import TaskSpec
from imitrl.policies.chunking import ChunkedPolicy, ChunkExecution

ACTION = Bounded(-2.0, 2.0, shape=(2,))
TASK = TaskSpec(action=ACTION, observation_dim=3)


def _rows(n: int = 64, episodes: int = 4, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, 3, generator=g)
    label = (obs[:, :2] * 0.8).clamp(-2, 2)  # a function of the state, inside the bounds
    episode, step = torch.arange(n) // (n // episodes), torch.arange(n) % (n // episodes)
    return TensorDict(
        {keys.OBSERVATION: obs, keys.EXPERT_ACTION: label, keys.EPISODE: episode, keys.STEP: step},
        [n],
    )


def _learner(seed: int = 0):
    return build("diffusion_unet", TASK, shared=dict(seed=seed))


# --------------------------------------------------------------- the registry entry
def test_the_entry_is_the_papers_recipe_at_cpu_widths():
    entry = registry.get("diffusion_unet")
    assert (entry.horizon, entry.history) == (16, 2)
    learner = _learner()
    assert learner.horizon == 16 and learner.history == 2 and learner.ema is not None
    assert learner.exploration == ExplorationType.RANDOM
    opt = learner.opt_pi
    assert isinstance(opt, torch.optim.AdamW)
    group = opt.param_groups[0]
    assert group["weight_decay"] == 1e-6 and group["betas"] == (0.95, 0.999)
    net = learner.policy.network
    assert net.schedule.kind == "squaredcos_cap_v2" and net.schedule.num_steps == 100
    assert learner.policy.execution.replan_every == 8
    # the recipe: cosine decay after a warm-up of min(500, steps // 10)
    bc = registry.fit_config("diffusion_unet", BCConfig(num_steps=2000, batch_size=64))
    assert (bc.lr_schedule, bc.warmup_steps) == ("cosine", 200)
    bc = registry.fit_config("diffusion_unet", BCConfig(num_steps=10_000, batch_size=64))
    assert bc.warmup_steps == 500
    # the paper's defaults, every one a documented field
    paper = UnetDiffusionConfig()
    assert paper.down_dims == (256, 512, 1024) and paper.lr == 1e-4
    assert (paper.obs_horizon, paper.horizon, paper.action_steps) == (2, 16, 8)
    assert (paper.ema_power, paper.warmup_steps, paper.sample_steps) == (0.75, 500, 10)


def test_a_fit_lowers_the_loss_and_the_same_seed_gives_the_same_digits():
    def run(seed: int):
        learner = _learner(seed)
        result = fit_bc(learner, _rows(), BCConfig(num_steps=40, batch_size=32, seed=seed))
        obs = TensorDict(
            {keys.OBSERVATION: torch.randn(3, 3, generator=torch.Generator().manual_seed(5)),
             IS_INIT: torch.ones(3, 1, dtype=torch.bool)},
            [3],
        )  # fmt: skip
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
            torch.manual_seed(7)  # sampling draws from the global RNG an evaluation seeds
            action = learner.policy(obs).get(keys.ACTION)
        return result.losses, action

    losses, action = run(0)
    assert losses[-10:].mean() < 0.7 * losses[:10].mean()
    again, action_again = run(0)
    assert torch.equal(losses, again) and torch.equal(action, action_again)
    other, _ = run(1)
    assert not torch.equal(losses, other)
    assert action.shape == (3, 2) and ((action >= -2) & (action <= 2)).all()


def test_the_loss_is_the_masked_epsilon_error_by_hand():
    learner = _learner()
    rows = learner.training_rows(_rows())
    pad = rows.get(CHUNK_PAD)
    assert pad.any() and (~pad).any()  # chunks run past the 16-step episodes' ends
    batch = rows[:8]
    net = learner.policy.network
    g = torch.Generator().manual_seed(0)  # the loss's generator, seeded as the entry seeds it
    k = torch.randint(0, 100, (8,), generator=g)
    eps = torch.randn(8, 16, 2, generator=g)
    x0 = batch.get(EXPERT_CHUNK) / 2.0  # bounds [-2, 2] -> [-1, 1]
    cond = net.normalizer(batch.get(OBS_HISTORY)).flatten(-2)
    with torch.no_grad():
        err = (net.unet(net.schedule.add_noise(x0, eps, k), k, cond) - eps).pow(2)
        keep = ~batch.get(CHUNK_PAD)
        expect = err[keep].sum() / (keep.sum() * 2)
        got = learner.loss(batch)["loss_diffusion"]
    assert torch.allclose(got, expect, rtol=1e-6, atol=0)


def test_labels_of_the_wrong_horizon_are_refused_by_name():
    learner = _learner()
    rows = learner.training_rows(_rows())
    rows.set(EXPERT_CHUNK, rows.get(EXPERT_CHUNK)[:, :8])
    with pytest.raises(ValueError, match=r"float \[N, 16, 2\].*add_chunk_labels"):
        learner.loss.check_labels(rows)


# --------------------------------------------------------------------- EMA learners
def _weights_a_fit_starts_from(learner) -> list[torch.Tensor]:
    """The policy's weights at the first step of a one-step fit (what it trains from)."""
    seen = []
    orig = learner.loss.objective

    def spy(batch, weights=None):
        seen.append([p.detach().clone() for p in learner.policy.parameters()])
        return orig(batch, weights)

    learner.loss.objective = spy
    fit_bc(learner, _rows(), BCConfig(num_steps=1, batch_size=32))
    return seen[0]


def test_a_fit_trains_the_weights_and_the_policy_acts_with_their_average():
    learner = _learner()
    before = [p.detach().clone() for p in learner.policy.parameters()]
    fit_bc(learner, _rows(), BCConfig(num_steps=5, batch_size=32))
    ema = learner.ema
    acting = list(learner.policy.parameters())
    assert all(torch.equal(a, b) for a, b in zip(acting, ema.averaged.parameters()))
    trained = [p.detach().clone() for p in ema.trained.parameters()]
    assert any(not torch.equal(a, b) for a, b in zip(acting, trained))  # 5 steps: not equal
    assert any(not torch.equal(a, b) for a, b in zip(trained, before))
    assert int(ema.step) == 5
    # a second fit continues from the trained weights (DAgger's warm start)
    assert all(torch.equal(a, b) for a, b in zip(_weights_a_fit_starts_from(learner), trained))


def test_a_checkpoint_carries_the_average_the_trained_weights_and_the_step():
    learner = _learner()
    fit_bc(learner, _rows(), BCConfig(num_steps=4, batch_size=32))
    state = learner.state_dict()
    assert any(k.startswith("ema.trained.") for k in state) and "ema.step" in state
    fresh = _learner(seed=3)
    fresh.load_state_dict(state)
    for a, b in zip(fresh.ema.trained.parameters(), learner.ema.trained.parameters()):
        assert torch.equal(a, b)
    for a, b in zip(fresh.policy.parameters(), learner.policy.parameters()):
        assert torch.equal(a, b)
    assert int(fresh.ema.step) == 4
    # the loss's generator is saved with the weights (sampling draws from the global RNG)
    assert torch.equal(fresh.loss.generator.get_state(), learner.loss.generator.get_state())
    # both continue with the same digits, given the optimiser's moments (a copy: a live
    # state dict shares Adam's step tensors)
    fresh.opt_pi.load_state_dict(copy.deepcopy(learner.opt_pi.state_dict()))
    a = fit_bc(learner, _rows(), BCConfig(num_steps=3, batch_size=32, seed=1)).losses
    b = fit_bc(fresh, _rows(), BCConfig(num_steps=3, batch_size=32, seed=1)).losses
    assert torch.equal(a, b)


def test_warm_up_then_cosine_by_hand():
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=2.0)
    schedule = _Cosine(opt, 110, warmup=10)
    assert schedule.scale(0) == 0.0 and schedule.scale(5) == 0.5
    assert schedule.scale(10) == 1.0
    assert schedule.scale(60) == pytest.approx(0.5)  # half-way through the decay
    assert schedule.scale(109) == pytest.approx(0.5 * (1 + math.cos(math.pi * 99 / 100)))
    schedule.at(5)
    assert opt.param_groups[0]["lr"] == 1.0
    schedule.restore()
    assert opt.param_groups[0]["lr"] == 2.0
    constant = _Cosine(opt, 100, warmup=4, kind="constant")
    assert [constant.scale(s) for s in (0, 2, 4, 50)] == [0.0, 0.5, 1.0, 1.0]
    with pytest.raises(ValueError, match="warmup_steps"):
        BCConfig(warmup_steps=-1)


# ------------------------------------------------------------- histories at act time
class _Recorder(TensorDictModuleBase):
    """A network that records the histories it is given and plans zeros."""

    def __init__(self) -> None:
        super().__init__()
        self.in_keys, self.out_keys = [OBS_HISTORY], [keys.ACTION]
        self.seen: list[torch.Tensor] = []

    def forward(self, td):
        self.seen.append(td.get(OBS_HISTORY).clone())
        td.set(keys.ACTION, torch.zeros(*td.batch_size, 4 * 1))
        return td


def test_the_acting_history_is_the_rows_history():
    # two lanes, replanning every step; lane 1 is reset at step 3
    net = _Recorder()
    policy = ChunkedPolicy(net, 1, ChunkExecution(4, execute=1), history=3)
    assert policy.in_keys == [keys.OBSERVATION, IS_INIT]
    obs = torch.arange(12.0).reshape(6, 2, 1) * torch.tensor([1.0, 100.0]).reshape(1, 2, 1)
    init = torch.zeros(6, 2, dtype=torch.bool)
    init[0] = True
    init[3, 1] = True
    for t in range(6):
        td = TensorDict({keys.OBSERVATION: obs[t], IS_INIT: init[t].unsqueeze(-1)}, [2])
        out = policy(td)
        assert OBS_HISTORY not in out.keys()  # the caller's tensordict gets no history
    # the rows of the same two lanes' episodes: lane 0 one episode of 6 steps, lane 1
    # two episodes (steps 0-2 and 3-5)
    episode = torch.tensor([[0, 1], [0, 1], [0, 1], [0, 2], [0, 2], [0, 2]])
    step = torch.tensor([[0, 0], [1, 1], [2, 2], [3, 0], [4, 1], [5, 2]])
    rows = TensorDict(
        {keys.OBSERVATION: obs.reshape(12, 1), keys.EPISODE: episode.reshape(12),
         keys.STEP: step.reshape(12)},
        [12],
    )  # fmt: skip
    expect = add_observation_history(rows, 3).get(OBS_HISTORY).reshape(6, 2, 3, 1)
    assert torch.equal(torch.stack(net.seen), expect)
    assert net.seen[0][1].flatten().tolist() == [100.0, 100.0, 100.0]  # padded by the first
    assert net.seen[4][1].flatten().tolist() == [700.0, 700.0, 900.0]  # after lane 1's reset


def test_a_history_the_network_does_not_read_is_refused():
    class Plain(_Recorder):
        def __init__(self) -> None:
            super().__init__()
            self.in_keys = [keys.OBSERVATION]

    with pytest.raises(ValueError, match="does not read the history"):
        ChunkedPolicy(Plain(), 1, ChunkExecution(4, execute=1), history=2)


def test_a_buffer_checkpoint_on_disk_restores_the_ema_learner_exactly(tmp_path):
    from imitrl.data import DemonstrationBuffer

    buffer = DemonstrationBuffer(action_spec=ACTION)
    rows = _rows()
    rows.set(keys.ACTION, rows.get(keys.EXPERT_ACTION))
    rows.set(keys.EXPERT_EXECUTED, torch.ones(64, dtype=torch.bool))
    rows.set(keys.ROUND, torch.zeros(64, dtype=torch.long))
    buffer.extend(rows)
    learner = _learner()
    fit_bc(learner, buffer, BCConfig(num_steps=3, batch_size=32))
    buffer.save(tmp_path / "ckpt", learner=learner)
    twin = _learner(seed=7)
    DemonstrationBuffer.load(tmp_path / "ckpt", learner=twin)
    for (name, a), b in zip(learner.state_dict().items(), twin.state_dict().values()):
        assert torch.equal(a, b), name  # weights, both EMA copies, step, generators
    a = fit_bc(learner, buffer, BCConfig(num_steps=2, batch_size=32, seed=2)).losses
    b = fit_bc(twin, buffer, BCConfig(num_steps=2, batch_size=32, seed=2)).losses
    assert torch.equal(a, b)
    for x, y in zip(learner.policy.parameters(), twin.policy.parameters()):
        assert torch.equal(x, y)  # the average continues with the loaded step's decay


def test_weights_set_on_the_policy_directly_become_the_trained_ones():
    learner = _learner()
    fit_bc(learner, _rows(), BCConfig(num_steps=3, batch_size=32))
    other = _learner(seed=9)
    learner.policy.load_state_dict(other.policy.state_dict())  # not the learner's own load
    start = _weights_a_fit_starts_from(learner)
    assert all(torch.equal(a, b) for a, b in zip(start, other.policy.parameters()))


def test_rows_that_carry_their_labels_and_histories_are_used_as_they_are():
    learner = _learner()
    rows = learner.training_rows(_rows())
    rows.set(EXPERT_CHUNK, torch.zeros_like(rows.get(EXPERT_CHUNK)))
    again = learner.training_rows(rows.exclude(keys.EPISODE, keys.STEP))  # no episodes needed
    assert torch.equal(again.get(EXPERT_CHUNK), rows.get(EXPERT_CHUNK))
    assert torch.equal(again.get(OBS_HISTORY), rows.get(OBS_HISTORY))


# --------------------------------------------------------------------- the camera
def test_the_resnet18_trunk_is_torchvisions_layout_with_groupnorm():
    from imitrl.learners.diffusion_unet.rgb_encoder import ResNet18GN

    trunk = ResNet18GN(3)
    # torchvision's resnet18 without its classifier: 11,689,512 - 513,000 parameters
    assert sum(p.numel() for p in trunk.parameters()) == 11_176_512
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in trunk.modules())
    norms = [m for m in trunk.modules() if isinstance(m, torch.nn.GroupNorm)]
    assert norms and all(m.num_groups == m.num_channels // 16 for m in norms)
    assert trunk(torch.zeros(2, 3, 76, 76)).shape == (2, 512, 3, 3)


def test_spatial_softmax_returns_the_keypoints_expected_coordinates():
    from imitrl.learners.diffusion_unet.rgb_encoder import SpatialSoftmax

    pool = SpatialSoftmax(1, 3, 5, keypoints=1)
    with torch.no_grad():
        pool.keypoints.weight.fill_(1.0)
        pool.keypoints.bias.zero_()
    features = torch.full((1, 1, 3, 5), -1e4)
    features[0, 0, 2, 1] = 0.0  # all the mass at row 2 (y = 1), column 1 (x = -0.5)
    assert torch.allclose(pool(features), torch.tensor([[-0.5, 1.0]]))
    uniform = pool(torch.zeros(1, 1, 3, 5))
    assert torch.allclose(uniform, torch.zeros(1, 2), atol=1e-6)  # the centre


def test_random_crops_take_each_sample_at_its_own_offset_and_acting_the_centre():
    from imitrl.learners.diffusion_unet.rgb_encoder import crop

    images = torch.arange(2 * 1 * 6 * 6, dtype=torch.float32).reshape(2, 1, 6, 6)
    centre = crop(images, (4, 4), None)
    assert torch.equal(centre, images[..., 1:5, 1:5])
    g = torch.Generator().manual_seed(0)
    out = crop(images, (4, 4), g)
    g2 = torch.Generator().manual_seed(0)
    top, left = torch.randint(0, 3, (2,), generator=g2), torch.randint(0, 3, (2,), generator=g2)
    for i in range(2):
        t, l0 = int(top[i]), int(left[i])
        assert torch.equal(out[i], images[i, :, t : t + 4, l0 : l0 + 4])


def test_a_camera_learner_fits_acts_with_image_histories_and_uses_the_image():
    from imitrl.learners.diffusion_unet import DIFFUSION_UNET

    unet = replace(DIFFUSION_UNET, down_dims=(16, 32), step_embed_dim=16, keypoints=4)
    camera = TaskSpec.from_specs(TASK.observation_dim, TASK.action, pixels=(40, 40, 3))
    learner = build("diffusion_unet", camera, options=unet, seed=0)
    assert learner.history_keys == (keys.OBSERVATION, keys.PIXELS)
    rows = _rows()
    g = torch.Generator().manual_seed(1)
    rows.set(keys.PIXELS, torch.randint(0, 256, (64, 40, 40, 3), dtype=torch.uint8, generator=g))
    result = fit_bc(learner, rows, BCConfig(num_steps=12, batch_size=16))
    assert torch.isfinite(result.losses).all()
    td = TensorDict(
        {keys.OBSERVATION: rows[:2].get(keys.OBSERVATION), keys.PIXELS: rows[:2].get(keys.PIXELS),
         IS_INIT: torch.ones(2, 1, dtype=torch.bool)},
        [2],
    )  # fmt: skip
    assert learner.policy.in_keys == [keys.OBSERVATION, keys.PIXELS, IS_INIT]
    net = learner.policy.network
    hist = learner.training_rows(rows)[:2]
    with torch.no_grad():
        cond = net.condition(hist)
        hist.set("pixels_history", 255 - hist.get("pixels_history"))
        assert not torch.equal(cond, net.condition(hist))  # the image changes the features
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        assert learner.policy(td).get(keys.ACTION).shape == (2, 2)
    with pytest.raises(ValueError, match="1x1 feature map"):
        build(
            "diffusion_unet",
            TaskSpec.from_specs(TASK.observation_dim, TASK.action, pixels=(24, 24, 3)),
            options=unet,
        )


class _Crash(Exception):
    pass


def test_dagger_with_diffusion_policy_resumes_to_the_uninterrupted_run(tmp_path):
    from imitrl.algorithms import DAggerConfig, EnvSource, dagger
    from imitrl.data import DemonstrationBuffer
    from imitrl.envs import make_env
    from imitrl.experts import pendulum_expert
    from imitrl.policies.chunking import chunk_env
    from imitrl.runtime import rollout_episodes

    def run(directory, resume=False, crash_at=None):
        torch.manual_seed(0)
        env = chunk_env(make_env("Pendulum-v1", seed=0, num_envs=2, max_episode_steps=12))
        task = TaskSpec(action=env.action_spec_unbatched, observation_dim=3)
        buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
        demo = make_env("Pendulum-v1", seed=1, max_episode_steps=12)
        buffer.extend(rollout_episodes(demo, pendulum_expert(), 2))

        def on_fit(k, learner):
            if k == crash_at:
                raise _Crash

        return dagger(
            EnvSource(env, exploration=None, max_steps=12),
            pendulum_expert(),
            lambda: build("diffusion_unet", task, shared=dict(seed=0)),
            buffer,
            DAggerConfig(
                rounds=3,
                episodes_per_round=2,
                warm_start=True,
                bc=BCConfig(num_steps=4, batch_size=16),
            ),
            checkpoint_dir=directory,
            resume=resume,
            on_fit=on_fit,
        )

    whole = run(tmp_path / "whole")
    with pytest.raises(_Crash):
        run(tmp_path / "cut", crash_at=2)  # after round 1's checkpoint
    resumed = run(tmp_path / "cut", resume=True)
    assert bool((whole.buffer.data == resumed.buffer.data).all())
    a, b = whole.learner.state_dict(), resumed.learner.state_dict()
    assert a.keys() == b.keys() and any(k.startswith("ema.trained") for k in a)
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_a_chunked_learner_acts_in_an_env_without_an_init_tracker_and_on_the_cli(tmp_path):
    from imitrl.cli import main
    from imitrl.envs import make_env
    from imitrl.evaluation import evaluate

    env = make_env("Pendulum-v1", seed=0, num_envs=2, max_episode_steps=10)
    task = TaskSpec(action=env.action_spec_unbatched, observation_dim=3)
    learner = build("diffusion_unet", task, shared=dict(seed=0))
    assert IS_INIT not in env.observation_spec.keys()
    first = evaluate(env, learner, 2, seed=2)
    assert first.num_episodes == 2 and first.mean_length == 10
    # samples come from the learner's own seeded generator (as flow's): a fresh learner
    # of the same seed, evaluated on the same seed, plays the same episodes
    twin = build("diffusion_unet", task, shared=dict(seed=0))
    assert evaluate(env, twin, 2, seed=2).mean_return == first.mean_return
    out = tmp_path / "run"
    args = ["bc", "--env", "Pendulum-v1", "--expert", "pendulum", "--loss", "diffusion_unet",
            "--steps", "3", "--batch-size", "16", "--demos", "1", "--eval-episodes", "1",
            "--max-episode-steps", "20", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    assert (out / "results.json").is_file()

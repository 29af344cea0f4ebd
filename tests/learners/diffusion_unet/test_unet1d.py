"""Diffusion Policy's pieces (issue 30): the temporal U-Net with FiLM, the noise schedule and
the DDPM/DDIM updates against hand computation, the EMA of the weights, observation
histories padded at episode starts."""

from __future__ import annotations

import math

import pytest
import torch

from imitrl.data.history import add_observation_history, observation_history
from imitrl.learners.diffusion_unet.noise_schedule import NoiseSchedule
from imitrl.learners.diffusion_unet.unet1d import ConditionalUnet1D, SinusoidalStepEmbedding
from imitrl.policies.ema import EMA

SMALL = {"down_dims": (16, 32, 64), "kernel_size": 5, "n_groups": 8, "step_embed_dim": 32}


def _net(seed: int = 0, cond: int = 6) -> ConditionalUnet1D:
    torch.manual_seed(seed)
    return ConditionalUnet1D(3, cond, **SMALL)


# ---------------------------------------------------------------------- the U-Net
def test_the_unet_maps_an_action_sequence_to_one_of_its_shape():
    net = _net()
    for T in (4, 8, 16):
        x = torch.randn(5, T, 3)
        out = net(x, torch.arange(5), torch.randn(5, 6))
        assert out.shape == (5, T, 3) and torch.isfinite(out).all()
    with pytest.raises(ValueError, match="divisible by 2 \\*\\* \\(levels - 1\\) = 4"):
        net(torch.randn(2, 6, 3), torch.zeros(2, dtype=torch.long), torch.randn(2, 6))
    with pytest.raises(ValueError, match="multiples of n_groups"):
        ConditionalUnet1D(3, 6, down_dims=(12, 24), n_groups=8)


def test_every_output_step_sees_the_whole_horizon():
    """The receptive field: the output at the first and at the last step depends on the
    input at every step of a 16-step sequence (kernel 5, three levels)."""
    net = _net()
    x = torch.randn(1, 16, 3, requires_grad=True)
    out = net(x, torch.tensor([3]), torch.randn(1, 6))
    for t in (0, 15):
        (grad,) = torch.autograd.grad(out[0, t].sum(), x, retain_graph=True)
        assert (grad[0].abs().sum(-1) > 0).all(), f"output step {t} misses some input steps"


def test_film_conditioning_is_used():
    net = _net()
    x, k = torch.randn(4, 8, 3), torch.full((4,), 7)
    cond = torch.randn(4, 6)
    a, b = net(x, k, cond), net(x, k, cond + 1.0)
    assert not torch.allclose(a, b)  # the observation features change the prediction
    c = net(x, torch.full((4,), 50), cond)
    assert not torch.allclose(a, c)  # and so does the diffusion step
    net(x, k, cond).pow(2).sum().backward()
    film = net.down[0][0].cond_encoder[1]
    assert film.weight.grad is not None and film.weight.grad.abs().sum() > 0


def test_the_step_embedding_is_the_sinusoid():
    emb = SinusoidalStepEmbedding(8)(torch.tensor([0.0, 2.0]))
    freqs = [10000 ** (-i / 3) for i in range(4)]
    expect = [[math.sin(2 * f) for f in freqs] + [math.cos(2 * f) for f in freqs]]
    assert torch.allclose(emb[1], torch.tensor(expect[0]), atol=1e-6)
    assert torch.equal(emb[0], torch.tensor([0.0] * 4 + [1.0] * 4))


def test_the_same_seed_gives_the_same_network_and_outputs():
    x, k, c = torch.randn(2, 8, 3), torch.tensor([1, 2]), torch.randn(2, 6)
    assert torch.equal(_net(3)(x, k, c), _net(3)(x, k, c))
    assert not torch.equal(_net(3)(x, k, c), _net(4)(x, k, c))


# ------------------------------------------------------------------ the schedule
def _abar(s: float) -> float:
    return math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2


def test_the_squaredcos_schedule_by_hand():
    K = 100
    schedule = NoiseSchedule(K)
    prod = 1.0
    for k in range(K):
        beta = min(1 - _abar((k + 1) / K) / _abar(k / K), 0.999)
        assert schedule.betas[k].item() == pytest.approx(beta, rel=1e-6)
        prod *= 1 - beta
    assert schedule.alphas_cumprod[-1].item() == pytest.approx(prod, rel=1e-4)
    # the chain reaches noise: abar_K is tiny, the first step barely noises
    assert schedule.alphas_cumprod[-1] < 1e-4 < 0.999 < schedule.alphas_cumprod[0]
    linear = NoiseSchedule(50, "linear", beta_start=1e-4, beta_end=0.2)
    assert linear.alphas_cumprod[-1].item() == pytest.approx(
        math.prod(1 - (1e-4 + (0.2 - 1e-4) * i / 49) for i in range(50)), rel=1e-4
    )


def test_forward_noising_and_one_ddim_step_by_hand():
    schedule = NoiseSchedule(100)
    x0, eps = torch.tensor([[0.5, -0.25]]), torch.tensor([[1.0, 2.0]])
    a = schedule.alphas_cumprod[40].item()
    xk = schedule.add_noise(x0, eps, torch.tensor([40]))
    assert torch.allclose(xk, math.sqrt(a) * x0 + math.sqrt(1 - a) * eps)
    assert schedule.ddim_timesteps(10) == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
    # one DDIM step from k = 40 to 30 with the true noise recovers x0 exactly ...
    prev = schedule.alphas_cumprod[30].item()
    out = schedule.ddim_step(eps, 40, 30, xk)
    assert torch.allclose(out, math.sqrt(prev) * x0 + math.sqrt(1 - prev) * eps, atol=1e-6)
    # ... and x0_hat is clipped to [-1, 1] before it is used
    big = schedule.ddim_step(torch.zeros(1, 2), 40, 30, torch.tensor([[5.0, -5.0]]))
    assert torch.allclose(big, math.sqrt(prev) * torch.tensor([[1.0, -1.0]]), atol=1e-6)
    # the last step (k = 0 -> none) returns x0_hat itself (abar before the chain: 1)
    last = schedule.ddim_step(eps, 0, -10, schedule.add_noise(x0, eps, torch.tensor([0])))
    assert torch.allclose(last, x0, atol=1e-5)


def test_one_ddpm_step_by_hand():
    schedule = NoiseSchedule(100, clip_sample=False)
    k, x, eps, z = 20, torch.tensor([[0.3]]), torch.tensor([[0.1]]), torch.tensor([[-0.7]])
    a, ap = schedule.alphas_cumprod[k].item(), schedule.alphas_cumprod[k - 1].item()
    alpha, beta = a / ap, 1 - a / ap
    x0 = (0.3 - math.sqrt(1 - a) * 0.1) / math.sqrt(a)
    mean = math.sqrt(ap) * beta / (1 - a) * x0 + math.sqrt(alpha) * (1 - ap) / (1 - a) * 0.3
    var = (1 - ap) / (1 - a) * beta
    expect = mean + math.sqrt(var) * -0.7
    assert schedule.ddpm_step(eps, k, x, z).item() == pytest.approx(expect, rel=1e-5)


def test_sampling_with_the_true_noise_model_returns_the_data():
    """With an oracle eps model for a point mass at x0, both samplers land on x0."""
    schedule = NoiseSchedule(100)
    x0 = torch.tensor([[0.4, -0.6, 0.1]])

    def oracle(x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        a = schedule.alphas_cumprod[k].reshape(-1, 1)
        return (x - a.sqrt() * x0) / (1 - a).sqrt()

    start = torch.randn(4, 3, generator=torch.Generator().manual_seed(0))
    ddim = schedule.sample(oracle, start, sampler="ddim", sample_steps=10)
    assert torch.allclose(ddim, x0.expand(4, 3), atol=1e-4)
    g = torch.Generator().manual_seed(1)
    ddpm = schedule.sample(oracle, start, sampler="ddpm", generator=g)
    assert torch.allclose(ddpm, x0.expand(4, 3), atol=1e-3)


def test_a_tiny_fit_lowers_the_noise_prediction_loss():
    torch.manual_seed(0)
    net, schedule = _net(cond=2), NoiseSchedule(100)
    cond = torch.randn(64, 2)
    actions = torch.tanh(cond[:, None, :1].expand(64, 8, 3) * torch.linspace(-1, 1, 8)[:, None])
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=1e-6)
    g = torch.Generator().manual_seed(0)

    def loss() -> torch.Tensor:
        k = torch.randint(0, 100, (64,), generator=g)
        eps = torch.randn(actions.shape, generator=g)
        return (net(schedule.add_noise(actions, eps, k), k, cond) - eps).pow(2).mean()

    with torch.no_grad():
        before = sum(loss().item() for _ in range(5)) / 5
    for _ in range(60):
        opt.zero_grad()
        loss().backward()
        opt.step()
    with torch.no_grad():
        after = sum(loss().item() for _ in range(5)) / 5
    assert after < 0.7 * before


# ----------------------------------------------------------------------------- EMA
def test_the_ema_decay_schedule_and_update_by_hand():
    model = torch.nn.Linear(2, 1)
    ema = EMA(model, power=0.75)
    assert ema.decay(0) == 0.0 and ema.decay(1) == 0.0  # the first updates copy the weights
    assert ema.decay(2) == pytest.approx(1 - 2**-0.75)
    assert ema.decay(10**9) == 0.9999  # capped
    w0 = model.weight.detach().clone()
    ema.update()  # decay 0: a copy
    assert torch.equal(ema.averaged.weight, w0)
    with torch.no_grad():
        model.weight.add_(1.0)
    ema.update()  # step 1: decay 0 again
    with torch.no_grad():
        model.weight.add_(1.0)
    d = ema.decay()
    expect = d * (w0 + 1.0) + (1 - d) * (w0 + 2.0)
    ema.update()
    assert torch.allclose(ema.averaged.weight, expect) and int(ema.step) == 3
    state = ema.state_dict()
    assert "step" in state and "averaged.weight" in state  # checkpoints carry the average


def test_ema_training_swaps_the_trained_weights_in_and_the_average_out():
    model = torch.nn.Linear(2, 1)
    ema = EMA(model)
    w0 = model.weight.detach().clone()
    with ema.trained_weights():
        assert torch.equal(model.weight, w0)  # the trained copy starts as the model
        with torch.no_grad():
            model.weight.add_(1.0)
        ema.update()  # decay 0: the average is the weights
        with torch.no_grad():
            model.weight.add_(2.0)
        ema.update()  # decay 0 again (step 1)
        with torch.no_grad():
            model.weight.add_(4.0)
        d = ema.decay()
        ema.update()
    average = d * (w0 + 3.0) + (1 - d) * (w0 + 7.0)
    assert torch.allclose(model.weight, average)  # outside: the model acts with the average
    assert torch.equal(ema.trained.weight, w0 + 7.0)
    with ema.trained_weights():  # the next fit continues from the trained weights, not the average
        assert torch.equal(model.weight, w0 + 7.0)
    assert torch.allclose(model.weight, average)


# ------------------------------------------------------------------------ histories
def test_histories_repeat_the_first_observation_at_episode_starts():
    # two episodes, rows shuffled: episode 7 has steps 0..3, episode 2 steps 0..1
    obs = torch.tensor([[10.0], [11.0], [12.0], [13.0], [20.0], [21.0]])
    episode = torch.tensor([7, 7, 7, 7, 2, 2])
    step = torch.tensor([0, 1, 2, 3, 0, 1])
    perm = torch.tensor([3, 5, 0, 2, 4, 1])
    h = observation_history(obs[perm], episode[perm], step[perm], 3)
    expect = {
        (7, 0): [10, 10, 10], (7, 1): [10, 10, 11], (7, 2): [10, 11, 12],
        (7, 3): [11, 12, 13], (2, 0): [20, 20, 20], (2, 1): [20, 20, 21],
    }  # fmt: skip
    for i, j in enumerate(perm.tolist()):
        key = (int(episode[j]), int(step[j]))
        assert h[i, :, 0].tolist() == expect[key]
    assert torch.equal(observation_history(obs, episode, step, 1)[:, 0], obs)
    with pytest.raises(ValueError, match="consecutive"):
        observation_history(obs, episode, torch.tensor([0, 1, 3, 4, 0, 1]), 2)


def test_add_observation_history_keeps_the_rows():
    from tensordict import TensorDict

    from imitrl import keys

    rows = TensorDict(
        {keys.OBSERVATION: torch.randn(5, 4), keys.EPISODE: torch.zeros(5, dtype=torch.long),
         keys.STEP: torch.arange(5)},
        batch_size=[5],
    )  # fmt: skip
    out = add_observation_history(rows, 2)
    assert out.get("observation_history").shape == (5, 2, 4)
    assert torch.equal(out.get("observation_history")[1:, 0], rows.get(keys.OBSERVATION)[:-1])
    assert "observation_history" not in rows.keys()

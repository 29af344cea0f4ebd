"""Diffusion behaviour cloning: TorchRL's ``DiffusionActor`` and ``DiffusionBCLoss`` in the action bounds.

The policy samples an action by running a DDPM reverse chain conditioned on the
observation (Chi et al. 2023, "Diffusion Policy"); the loss is TorchRL's
epsilon-prediction objective ``E_{t, eps} ||eps - eps_theta(sqrt(abar_t) a + sqrt(1 - abar_t) eps, s, t)||^2``.
A generative policy can represent several modes of the expert's action at one state,
where a regression loss predicts their mean.

What this module adds around the two TorchRL classes, and why:

* actions are diffused in ``[-1, 1]`` and mapped to the spec's bounds afterwards
  (the DDPM prior is a unit Gaussian; Pendulum's torque lives in ``[-2, 2]``);
* a score network that sees ``t / num_steps`` instead of the raw step index
  (``DiffusionActor`` concatenates the integer step, up to ``num_steps - 1``, to the
  network input);
* a noise schedule that reaches noise: torchrl 0.14.1's defaults (100 steps, betas
  from 1e-4 to 0.02) leave ``abar_T = 0.36``, so sampling would start from a unit
  Gaussian that the chain was never trained to denoise. Here ``beta_end`` defaults to
  0.2 over 50 steps (``abar_T = 0.005``);
* explicit generators: both classes draw from the global RNG; the policy's samples
  and the loss's noise draw from their own seeded generators instead (same seed,
  same digits, whatever else ran in between).

Exploration: ``RANDOM`` samples (a fresh Gaussian latent per call); ``DETERMINISTIC``
starts TorchRL's chain from a zero latent without injected noise, which is repeatable
but not a sample and may pick one mode everywhere.

Few-step sampling (``sampler="ddim"``): the same trained network, sampled by DDIM
(Song et al. 2021, eta = 0) on ``sample_steps`` of the ``num_steps`` training steps,
``tau_1 > ... > tau_S`` evenly spaced from ``T - 1`` to 0 (:func:`ddim_sample`):

    x0_hat = (x_tau - sqrt(1 - abar_tau) eps) / sqrt(abar_tau),   clipped to [-1, 1]
    x_prev = sqrt(abar_prev) x0_hat + sqrt(1 - abar_prev) eps     (abar after tau_S: 1)

deterministic given the starting latent (drawn as for DDPM), so ``S`` network calls
per action instead of ``T``. TorchRL's ``DiffusionActor`` has only the DDPM chain; the
schedule ``abar`` is recomputed here from the same betas (``torch.linspace(beta_start,
beta_end, T)``, the actor's own formula; a test checks they agree).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from tensordict.nn.probabilistic import interaction_type
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import DiffusionActor

from imitrl import keys
from imitrl.learners.defaults import HIDDEN
from imitrl.rng import SavedGenerator, rng_from

__all__ = ["SAMPLERS", "DiffusionPolicy", "ScoreNetwork", "ddim_sample", "ddim_sample_guided"]


SAMPLERS = ("ddpm", "ddim")


NORMALIZED = "diffusion_action"
"""key of the action in ``[-1, 1]``, before it is mapped to the bounds"""


class ScoreNetwork(nn.Module):
    """``eps_theta([noisy_action, observation, t]) -> eps``: an MLP with the step scaled to ``[0, 1)``.

    Input ``[..., action_dim + observation_dim + 1]`` (the layout ``DiffusionActor`` and
    ``DiffusionBCLoss`` build), output ``[..., action_dim]``.
    """

    def __init__(
        self, action_dim: int, observation_dim: int, hidden: Sequence[int], num_steps: int
    ) -> None:
        super().__init__()
        sizes = [action_dim + observation_dim + 1, *hidden]
        layers: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(a, b), nn.SiLU()]
        layers.append(nn.Linear(sizes[-1], action_dim))
        self.net = nn.Sequential(*layers)
        self.num_steps = int(num_steps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([x[..., :-1], x[..., -1:] / self.num_steps], dim=-1))


def ddim_sample(
    score: nn.Module,
    obs: torch.Tensor,
    x: torch.Tensor,
    alphas_cumprod: torch.Tensor,
    sample_steps: int,
) -> torch.Tensor:
    """DDIM (eta = 0) from the latent ``x`` ``[..., d]`` on ``sample_steps`` of the ``T`` steps.

    ``score([x, obs, t]) -> eps`` as ``DiffusionActor`` calls it (``t`` the raw step
    index); ``alphas_cumprod`` ``[T]``. Returns ``x0`` ``[..., d]`` (module docstring).
    """
    T = alphas_cumprod.shape[0]
    alphas_cumprod = alphas_cumprod.to(x.device)
    taus = torch.linspace(T - 1, 0, int(sample_steps)).round().long().unique_consecutive()
    for i, tau in enumerate(taus.tolist()):
        abar = alphas_cumprod[tau]
        abar_prev = alphas_cumprod[taus[i + 1]] if i + 1 < len(taus) else torch.tensor(1.0)
        t = torch.full((*x.shape[:-1], 1), float(tau), device=x.device)
        eps = score(torch.cat([x, obs.to(x.dtype), t], dim=-1))
        x0 = ((x - (1 - abar).sqrt() * eps) / abar.sqrt()).clamp(-1.0, 1.0)
        x = abar_prev.sqrt() * x0 + (1 - abar_prev).sqrt() * eps
    return x


def ddim_sample_guided(
    score: nn.Module,
    obs: torch.Tensor,
    x: torch.Tensor,
    alphas_cumprod: torch.Tensor,
    sample_steps: int,
    target: torch.Tensor,
    weights: torch.Tensor,
    guidance: float,
) -> torch.Tensor:
    """:func:`ddim_sample` pulled towards ``target`` ``[..., d]`` (in ``[-1, 1]``) where
    ``weights`` say: real-time chunking's inpainting (Black et al. 2025) on DDIM's clean
    prediction. Each step's ``x0_hat`` moves by ``(1 - tau) w J^T (W (y - x0_hat))``, ``J`` its
    Jacobian in ``x`` (one vector-Jacobian product), ``tau = sqrt(abar) / (sqrt(abar) +
    sqrt(1 - abar))`` the flow time of the step (the same signal-to-noise ratio) and ``w =
    min(guidance, (1 - tau) / (tau r^2))`` as for a flow
    (:meth:`~imitrl.learners.flow.policy.FlowPolicy.sample_guided`); ``eps`` moves with it
    (``x`` unchanged), so zero weights give :func:`ddim_sample`'s steps."""
    T = alphas_cumprod.shape[0]
    alphas_cumprod = alphas_cumprod.to(x.device)
    taus = torch.linspace(T - 1, 0, int(sample_steps)).round().long().unique_consecutive()
    for i, step in enumerate(taus.tolist()):
        abar = alphas_cumprod[step]
        abar_prev = alphas_cumprod[taus[i + 1]] if i + 1 < len(taus) else torch.tensor(1.0)
        t = torch.full((*x.shape[:-1], 1), float(step), device=x.device)
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            eps = score(torch.cat([xg, obs.to(x.dtype), t], dim=-1))
            x0 = (xg - (1 - abar).sqrt() * eps) / abar.sqrt()
            (g,) = torch.autograd.grad(x0, xg, grad_outputs=weights * (target - x0))
        tau = float(abar.sqrt() / (abar.sqrt() + (1 - abar).sqrt()))
        r2 = (1 - tau) ** 2 / (tau**2 + (1 - tau) ** 2)
        w = min(guidance, (1 - tau) / (tau * r2))
        shift = (1 - tau) * w * g  # x0_hat moves; x stays, so eps moves the other way
        eps = eps.detach() - abar.sqrt() / (1 - abar).sqrt() * shift
        x0 = (x0.detach() + shift).clamp(-1.0, 1.0)
        x = abar_prev.sqrt() * x0 + (1 - abar_prev).sqrt() * eps
    return x


class DiffusionPolicy(SavedGenerator, TensorDictModuleBase):
    """``OBSERVATION -> ACTION`` by a DDPM reverse chain, inside the bounds of ``action_spec``.

    Args:
        observation_dim: length of the observation vector ``[..., d]``.
        action_spec: ``Bounded`` spec of shape ``[m]``; actions are written float32 ``[..., m]``.
        hidden: hidden layer sizes of the score network.
        num_steps: denoising steps ``T`` of training (and of the DDPM chain).
        beta_start, beta_end: the linear noise schedule.
        seed: initialisation and sampling seed.
        sampler: ``"ddpm"`` (TorchRL's chain, ``T`` network calls per action) or
            ``"ddim"`` (``sample_steps`` calls, :func:`ddim_sample`).
        sample_steps: DDIM steps (ignored by DDPM).

    Writes ``"diffusion_action"`` (the sample in ``[-1, 1]``) and ``ACTION``.
    """

    def __init__(
        self,
        observation_dim: int,
        action_spec: Bounded,
        *,
        hidden: Sequence[int] = HIDDEN,
        num_steps: int = 50,
        beta_start: float = 1e-4,
        beta_end: float = 0.2,
        seed: int = 0,
        sampler: str = "ddpm",
        sample_steps: int = 8,
    ) -> None:
        super().__init__()
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
        if sampler == "ddim" and not 1 <= sample_steps <= num_steps:
            raise ValueError(
                f"sample_steps must be in [1, num_steps={num_steps}], got {sample_steps}"
            )
        self.sampler, self.sample_steps = sampler, int(sample_steps)
        if not isinstance(action_spec, Bounded) or len(action_spec.shape) != 1:
            raise ValueError(
                f"a diffusion policy needs a Bounded action spec of shape [action_dim], got {action_spec!r}"
            )
        if num_steps < 1:
            raise ValueError(f"num_steps must be positive, got {num_steps}")
        dim = int(action_spec.shape[0])
        self.in_keys = [keys.OBSERVATION]
        self.out_keys = [NORMALIZED, keys.ACTION]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            score = ScoreNetwork(dim, int(observation_dim), hidden, num_steps)
        self.actor = DiffusionActor(
            action_dim=dim,
            score_network=score,
            num_steps=num_steps,
            beta_start=beta_start,
            beta_end=beta_end,
            in_keys=[keys.OBSERVATION],
            out_keys=[NORMALIZED],
        )
        # plain attributes, not registered: the network already belongs to the actor, and
        # the state dict (checkpoints) stays what it was before DDIM
        object.__setattr__(self, "_score", score)
        betas = torch.linspace(beta_start, beta_end, num_steps)  # DiffusionActor's schedule
        self._alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)
        self.register_buffer("low", action_spec.space.low.float().clone())
        self.register_buffer("high", action_spec.space.high.float().clone())
        self.generator = torch.Generator().manual_seed(int(seed) + 1)

    def normalize(self, action: torch.Tensor) -> torch.Tensor:
        """Bounds -> ``[-1, 1]``."""
        return 2 * (action.float() - self.low) / (self.high - self.low) - 1

    def _latent(self, obs: torch.Tensor) -> torch.Tensor:
        shape = (*obs.shape[:-1], self.low.shape[0])
        if interaction_type() == InteractionType.DETERMINISTIC:
            return torch.zeros(shape, device=obs.device)  # as TorchRL's chain starts here
        return torch.randn(shape, generator=self.generator).to(obs.device)

    def inpaint(
        self,
        tensordict: TensorDictBase,
        target: torch.Tensor,
        weights: torch.Tensor,
        guidance: float,
    ) -> torch.Tensor:
        """The action ``[..., m]`` sampled by DDIM (``sample_steps`` steps, whichever
        ``sampler`` the policy acts with: guidance needs the clean prediction at each step)
        and guided towards ``target`` (in the bounds) with ``weights``
        (:func:`ddim_sample_guided`): real-time chunking
        (:class:`~imitrl.policies.latency.DelayedChunkPolicy`, mode ``rtc``)."""
        obs = tensordict.get(keys.OBSERVATION)
        y = self.normalize(target.to(obs.device))
        x = ddim_sample_guided(
            self._score, obs, self._latent(obs), self._alphas_cumprod, self.sample_steps,
            y, weights.to(y.dtype), guidance,
        ).clamp(-1.0, 1.0)  # fmt: skip
        return self.low + (self.high - self.low) * (x + 1) / 2

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.sampler == "ddim":
            obs = tensordict.get(keys.OBSERVATION)
            x = ddim_sample(
                self._score, obs, self._latent(obs), self._alphas_cumprod, self.sample_steps
            )
            tensordict.set(NORMALIZED, x)
        else:
            with rng_from(self.generator):
                tensordict = self.actor(tensordict)
        x = tensordict.get(NORMALIZED).clamp(-1.0, 1.0)
        tensordict.set(keys.ACTION, self.low + (self.high - self.low) * (x + 1) / 2)
        return tensordict

"""Flow-matching behaviour cloning: a rectified flow from noise to the expert's action.

Conditional flow matching with the straight (rectified-flow) path of Lipman et al.
2023 and Liu et al. 2023: for a label ``x_1`` (the action, or a chunk of ``H``
actions, mapped to ``[-1, 1]``), noise ``x_0 ~ N(0, I)`` and ``t ~ U(0, 1)``,

    x_t = (1 - t) x_0 + t x_1,        loss = E || v_theta(x_t, s, t) - (x_1 - x_0) ||^2,

averaged over the entries of the label that are not padding (a chunk's entries past
the episode's end, :mod:`imitrl.data.chunks`; they still enter ``x_t`` as the label
holds them, the episode's last action repeated, but their error carries no weight). The policy samples by integrating
``dx/dt = v_theta(x, s, t)`` from ``x_0`` at ``t = 0`` to ``t = 1`` with
``num_steps`` Euler steps (a few suffice: the learned paths are nearly straight).
Like diffusion, it is generative: it can keep several modes of the expert's action.

Exploration: ``RANDOM`` draws ``x_0`` from the policy's own seeded generator, or takes
it from ``POLICY_NOISE`` when the input carries it (a chunked policy that holds one
draw per episode, :class:`~imitrl.policies.chunking.ChunkExecution`'s ``hold_noise``:
the learned map from noise to action is deterministic, so the same ``x_0`` keeps
choosing the same mode at every replan); ``DETERMINISTIC`` starts from ``x_0 = 0``
(repeatable, not a sample).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from tensordict.nn.probabilistic import interaction_type
from torch import nn
from torchrl.data import Bounded

from imitrl import keys
from imitrl.learners.defaults import HIDDEN
from imitrl.policies.normalization import ObservationNormalizer
from imitrl.rng import SavedGenerator

__all__ = ["FlowPolicy", "VelocityNetwork"]


class VelocityNetwork(nn.Module):
    """``v_theta(x [..., d], s [..., o], t [..., 1]) -> [..., d]``: an MLP over their concatenation."""

    def __init__(
        self,
        action_dim: int,
        observation_dim: int,
        hidden: Sequence[int],
        normalizer: ObservationNormalizer | None,
    ) -> None:
        super().__init__()
        sizes = [action_dim + observation_dim + 1, *hidden]
        layers: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(a, b), nn.SiLU()]
        layers.append(nn.Linear(sizes[-1], action_dim))
        self.net = nn.Sequential(*layers)
        self.normalizer = normalizer

    def forward(self, x: torch.Tensor, obs: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        obs = obs.float() if self.normalizer is None else self.normalizer(obs.float())
        return self.net(torch.cat([x, obs, t], dim=-1))


class FlowPolicy(SavedGenerator, TensorDictModuleBase):
    """``OBSERVATION -> ACTION`` by ``num_steps`` Euler steps of a learned flow, in the bounds.

    Args:
        observation_dim: length of the observation vector ``[..., o]``.
        action_spec: ``Bounded`` spec ``[d]`` (for chunks the tiled spec ``[H * m]``,
            :func:`imitrl.policies.chunking.tile_spec`); actions are float32 ``[..., d]``.
        hidden: hidden layer sizes of the velocity network.
        num_steps: Euler steps per action (each costs one network call).
        normalize: normalise observations inside the network (fitted by ``Learner.prepare``).
        seed: initialisation and sampling seed.
    """

    def __init__(
        self,
        observation_dim: int,
        action_spec: Bounded,
        *,
        hidden: Sequence[int] = HIDDEN,
        num_steps: int = 8,
        normalize: bool = True,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if not isinstance(action_spec, Bounded) or len(action_spec.shape) != 1:
            raise ValueError(f"a flow policy needs a Bounded action spec [d], got {action_spec!r}")
        if int(num_steps) != num_steps or num_steps < 1:
            raise ValueError(f"num_steps must be a positive integer, got {num_steps!r}")
        self.in_keys, self.out_keys = [keys.OBSERVATION], [keys.ACTION]
        self.num_steps = int(num_steps)
        self.normalizer = ObservationNormalizer((int(observation_dim),)) if normalize else None
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            dim = int(action_spec.shape[0])
            self.velocity = VelocityNetwork(dim, int(observation_dim), hidden, self.normalizer)
        self.register_buffer("low", action_spec.space.low.float().clone())
        self.register_buffer("high", action_spec.space.high.float().clone())
        self.generator = torch.Generator().manual_seed(int(seed) + 1)

    def normalize(self, action: torch.Tensor) -> torch.Tensor:
        """Bounds -> ``[-1, 1]``."""
        return 2 * (action.float() - self.low) / (self.high - self.low) - 1

    def draw_noise(self, n: int) -> torch.Tensor:
        """``[n, d]`` starting noise from the policy's generator (what ``RANDOM`` draws)."""
        # drawn on the CPU from the seeded generator, then moved: one seed, one draw, any device
        return torch.randn(int(n), self.low.shape[0], generator=self.generator).to(self.low.device)

    def sample(self, obs: torch.Tensor, x0: torch.Tensor) -> torch.Tensor:
        """Euler-integrate the flow from ``x0`` ``[..., d]`` at ``t = 0`` to ``t = 1``."""
        x, dt = x0, 1.0 / self.num_steps
        for k in range(self.num_steps):
            t = torch.full((*x.shape[:-1], 1), k * dt, device=x.device)
            x = x + dt * self.velocity(x, obs, t)
        return x

    def sample_guided(
        self,
        obs: torch.Tensor,
        x0: torch.Tensor,
        target: torch.Tensor,
        weights: torch.Tensor,
        guidance: float,
    ) -> torch.Tensor:
        """:meth:`sample` pulled towards ``target`` ``[..., d]`` (in ``[-1, 1]``) where
        ``weights`` ``[..., d]`` say: real-time chunking's inpainting (Black et al. 2025,
        Algorithm 1, with Pokle et al.'s PiGDM guidance). At each Euler step ``tau``, the
        clean sample the flow predicts, ``x1 = x + (1 - tau) v``, is compared with the
        target, and the weighted error is sent back through ``x1``'s Jacobian (one
        vector-Jacobian product): ``v += min(guidance, (1 - tau) / (tau r^2)) J^T (W (y -
        x1))`` with ``r^2 = (1 - tau)^2 / (tau^2 + (1 - tau)^2)``."""
        x, dt = x0, 1.0 / self.num_steps
        for k in range(self.num_steps):
            tau = k * dt
            t = torch.full((*x.shape[:-1], 1), tau, device=x.device)
            with torch.enable_grad():
                xg = x.detach().requires_grad_(True)
                v = self.velocity(xg, obs, t)
                x1 = xg + (1 - tau) * v
                (g,) = torch.autograd.grad(x1, xg, grad_outputs=weights * (target - x1))
            r2 = (1 - tau) ** 2 / (tau**2 + (1 - tau) ** 2)
            w = guidance if tau == 0 else min(guidance, (1 - tau) / (tau * r2))
            x = x + dt * (v.detach() + w * g)
        return x

    def inpaint(
        self,
        tensordict: TensorDictBase,
        target: torch.Tensor,
        weights: torch.Tensor,
        guidance: float,
    ) -> torch.Tensor:
        """The action ``[..., d]`` sampled as :meth:`forward` samples it (the same starting
        noise), guided towards ``target`` (in the action's bounds) with ``weights``
        (:meth:`sample_guided`); what a latency-aware chunked policy asks for
        (:class:`~imitrl.policies.latency.DelayedChunkPolicy`, mode ``rtc``)."""
        obs = tensordict.get(keys.OBSERVATION)
        x0 = self._start(tensordict, obs)
        y = self.normalize(target.to(obs.device))
        x = self.sample_guided(obs, x0, y, weights.to(x0.dtype), guidance).clamp(-1.0, 1.0)
        return self.low + (self.high - self.low) * (x + 1) / 2

    def _start(self, tensordict: TensorDictBase, obs: torch.Tensor) -> torch.Tensor:
        """The starting noise ``x_0``: zero (``DETERMINISTIC``), ``POLICY_NOISE`` where the
        input holds it, else a fresh draw."""
        shape = (*obs.shape[:-1], self.low.shape[0])
        held = tensordict.get(keys.POLICY_NOISE, None)
        if interaction_type() == InteractionType.DETERMINISTIC:
            return torch.zeros(shape, device=obs.device)
        if held is not None:
            if tuple(held.shape) != shape or not held.dtype.is_floating_point:
                raise ValueError(
                    f"{keys.POLICY_NOISE!r} must be float {list(shape)} (the observation's "
                    f"batch, then the action's {shape[-1]} entries), got {held.dtype} "
                    f"{list(held.shape)}"
                )
            return held.float().to(obs.device)
        return torch.randn(shape, generator=self.generator).to(obs.device)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(keys.OBSERVATION)
        x = self.sample(obs, self._start(tensordict, obs)).clamp(-1.0, 1.0)
        tensordict.set(keys.ACTION, self.low + (self.high - self.low) * (x + 1) / 2)
        return tensordict

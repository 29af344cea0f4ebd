"""The minimal iterative policy (MIP): two supervised regression steps, noise in training only.

"Much Ado About Noising" (Pan et al., ICLR 2026, arXiv 2512.01809) finds that flow and
diffusion policies owe their success to supervised iterative computation paired with
noise in training, not to fitting a multimodal distribution, and proposes MIP as the
minimal policy with both. One network ``f(x, s, t)`` (the flow policies' velocity MLP over
an action ``x`` mapped to ``[-1, 1]``, the observation ``s`` and a time ``t``):

* **acting**: ``a_0 = f(0, s, 0)``, then ``a = f(a_0, s, t*)``: two calls, no noise;
* **training** on a label ``a`` (``[-1, 1]``) with ``eps ~ N(0, I)``:
  ``loss = ||f(0, s, 0) - a||^2 / t*^2 + ||f(a + (1 - t*) eps, s, t*) - a||^2 / (1 - t*)^2``,
  averaged over the label's entries that are not padding (a chunk's entries past its
  episode's end, :mod:`imitrl.data.chunks`): the reference implementation's ``mip_loss``
  (``mip/losses.py``, its l2 norm squared over the action, meaned over the batch) divided by
  the action's length, a constant.

``t* = 0.9`` is the reference's ``t_two_step`` (its ``OptimizationConfig``); the
sampler is its ``mip_sampler`` (the first prediction fed to the second unscaled).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded

from imitrl import keys
from imitrl.learners.action_loss import NormalizedActionLoss
from imitrl.learners.defaults import HIDDEN
from imitrl.learners.flow.policy import VelocityNetwork
from imitrl.policies.normalization import ObservationNormalizer
from imitrl.system.ranks import rows_drawn

__all__ = ["T_STAR", "MIPLoss", "MIPPolicy"]

T_STAR = 0.9
"""the second step's time, and the training noise's scale ``1 - t*`` (the reference's
``t_two_step``)"""


class MIPPolicy(TensorDictModuleBase):
    """``OBSERVATION -> ACTION`` by MIP's two steps (module docstring), in the bounds.

    Args:
        observation_dim: length of the observation vector.
        action_spec: ``Bounded`` spec ``[d]`` (for chunks the tiled spec ``[H * m]``).
        hidden: hidden layer sizes of the network.
        t_star: the second step's time.
        normalize: normalise observations inside the network (fitted by ``Learner.prepare``).
        seed: initialisation seed.
    """

    def __init__(
        self,
        observation_dim: int,
        action_spec: Bounded,
        *,
        hidden: Sequence[int] = HIDDEN,
        t_star: float = T_STAR,
        normalize: bool = True,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if not isinstance(action_spec, Bounded) or len(action_spec.shape) != 1:
            raise ValueError(f"a MIP policy needs a Bounded action spec [d], got {action_spec!r}")
        if not 0.0 < t_star < 1.0:
            raise ValueError(f"t_star must be in (0, 1), got {t_star}")
        self.in_keys, self.out_keys = [keys.OBSERVATION], [keys.ACTION]
        self.t_star = float(t_star)
        self.normalizer = ObservationNormalizer((int(observation_dim),)) if normalize else None
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            dim = int(action_spec.shape[0])
            self.net = VelocityNetwork(dim, int(observation_dim), hidden, self.normalizer)
        self.register_buffer("low", action_spec.space.low.float().clone())
        self.register_buffer("high", action_spec.space.high.float().clone())

    def normalize(self, action: torch.Tensor) -> torch.Tensor:
        """Bounds -> ``[-1, 1]``."""
        return 2 * (action.float() - self.low) / (self.high - self.low) - 1

    def step(self, x: torch.Tensor, obs: torch.Tensor, t: float) -> torch.Tensor:
        """``f(x, s, t)`` at one time ``t`` for the batch ``x [..., d]``."""
        return self.net(x, obs, torch.full((*x.shape[:-1], 1), t, device=x.device))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(keys.OBSERVATION)
        zero = torch.zeros((*obs.shape[:-1], self.low.shape[0]), device=obs.device)
        first = self.step(zero, obs, 0.0)
        x = self.step(first, obs, self.t_star).clamp(-1.0, 1.0)
        tensordict.set(keys.ACTION, self.low + (self.high - self.low) * (x + 1) / 2)
        return tensordict


class MIPLoss(NormalizedActionLoss):
    """MIP's training loss of a :class:`MIPPolicy` (module docstring).

    Args:
        policy: the policy trained.
        chunked: labels are chunks under ``EXPERT_CHUNK`` with the mask ``CHUNK_PAD``;
            False: actions under ``EXPERT_ACTION``.
        seed: seed of the training noise.

    Returns ``loss_mip``.
    """

    out_keys = ["loss_mip"]
    what = "MIP labels"

    def __init__(self, policy: MIPPolicy, *, chunked: bool = False, seed: int = 0) -> None:
        if not isinstance(policy, MIPPolicy):
            raise ValueError(f"expected a MIPPolicy, got {type(policy).__name__}")
        super().__init__(policy, chunked=chunked, seed=seed)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.tensor_keys.observation)
        a = self.labels(tensordict)
        n, d = a.shape
        g, t = self.generator, self.policy.t_star  # CPU draws per row (data-parallel ranks)
        eps = rows_drawn(lambda m: torch.randn(m, d, generator=g), n).to(a.device)
        first = self.policy.step(torch.zeros_like(a), obs, 0.0)
        second = self.policy.step(a + (1 - t) * eps, obs, t)
        err = (first - a) ** 2 / t**2 + (second - a) ** 2 / (1 - t) ** 2  # [N, d]
        return TensorDict({"loss_mip": self.mean_error(err, tensordict)}, batch_size=[])

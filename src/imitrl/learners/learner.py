"""The learner contract: one object that ``fit_bc``, ``dagger`` and ``evaluate`` take.

A :class:`Learner` holds

* ``policy``: a TensorDictModule ``OBSERVATION -> ACTION`` (what rollouts run);
* ``loss``: an :class:`~imitrl.objectives.base.ImitationLoss` over that policy (the
  loss is chosen once, when the learner is built);
* ``opt_pi``: the optimizer over the policy's parameters;
* ``exploration``: how the policy acts when rolled out or evaluated
  (``DETERMINISTIC``: the greedy action / mode; ``RANDOM``: a sample);
* ``normalizer``: an optional :class:`ObservationNormalizer` inside the policy's
  network, fitted to the demonstrations by :meth:`Learner.prepare`;
* ``ema``: an optional :class:`~imitrl.policies.ema.EMA` of the policy's weights: a fit
  trains the weights and averages them after every step, and the policy acts (is rolled
  out, evaluated, saved) with the average (any loss can use it: ``Learner(..., ema=EMA(policy))``);
* ``horizon`` and ``history``: what the rows of a fit must carry besides the buffer's
  columns: the expert's next ``horizon`` labels (:func:`~imitrl.data.chunks.add_chunk_labels`)
  and the last ``history`` observations (:func:`~imitrl.data.history.add_observation_history`).
  ``fit_bc`` adds both, from the rows' episodes (:meth:`Learner.training_rows`), so DAgger's
  relabelled rounds get them the same way as the demonstrations.

:class:`~imitrl.learners.ActorCritic` is a Learner with a value head; the loss
registry builds Learners; any user policy becomes one with ``Learner(policy, loss,
opt)``.
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK, add_chunk_labels
from imitrl.data.history import add_observation_history, history_key
from imitrl.learners.saved_state import check_saved_state
from imitrl.objectives.base import ImitationLoss
from imitrl.policies.ema import EMA
from imitrl.policies.normalization import ObservationNormalizer
from imitrl.system.device import module_device, resolve_device

if TYPE_CHECKING:
    from typing_extensions import Self

__all__ = ["Learner"]


class Learner(nn.Module):
    """A policy, the loss that trains it, its optimizer and how it acts (module docstring).

    Args:
        policy: ``OBSERVATION -> ACTION``.
        loss: an ``ImitationLoss`` over ``policy`` (wrap any other TorchRL loss in
            :class:`~imitrl.objectives.SummedLoss`).
        opt_pi: optimizer over ``policy``'s parameters.
        exploration: how the policy acts in rollouts and evaluation.
        normalizer: the observation normaliser inside ``policy``'s network, or None.
        ema: a moving average of ``policy``'s weights to act with, or None.
        horizon: ``H`` of a chunked policy's labels, or None.
        history: observations a row must carry (its last ``history``, oldest first),
            or None.
        history_keys: the observation keys whose history the rows carry.
    """

    def __init__(
        self,
        policy: TensorDictModuleBase,
        loss: ImitationLoss,
        opt_pi: torch.optim.Optimizer,
        *,
        exploration: ExplorationType = ExplorationType.DETERMINISTIC,
        normalizer: ObservationNormalizer | None = None,
        ema: EMA | None = None,
        horizon: int | None = None,
        history: int | None = None,
        history_keys: tuple = (keys.OBSERVATION,),
    ) -> None:
        super().__init__()
        if not isinstance(policy, TensorDictModuleBase):
            raise ValueError(f"policy must be a TensorDictModule, got {type(policy).__name__}")
        if not isinstance(loss, ImitationLoss):
            raise ValueError(
                f"loss must be an imitrl ImitationLoss, got {type(loss).__name__} "
                "(wrap a TorchRL LossModule in imitrl.objectives.SummedLoss)"
            )
        if not isinstance(opt_pi, torch.optim.Optimizer):
            raise ValueError(f"opt_pi must be a torch optimizer, got {type(opt_pi).__name__}")
        if exploration not in (ExplorationType.DETERMINISTIC, ExplorationType.RANDOM):
            raise ValueError(f"exploration must be DETERMINISTIC or RANDOM, got {exploration}")
        self.policy = policy
        self.loss = loss
        self.opt_pi = opt_pi
        self.exploration = exploration
        self.normalizer = normalizer
        if ema is not None and (not isinstance(ema, EMA) or ema._model is not policy):
            raise ValueError("ema must be an imitrl EMA of this learner's policy: EMA(policy)")
        self.ema = ema
        for name, value in (("horizon", horizon), ("history", history)):
            if value is not None and (isinstance(value, bool) or int(value) != value or value < 1):
                raise ValueError(f"{name} must be a positive integer or None, got {value!r}")
        self.horizon = None if horizon is None else int(horizon)
        self.history = None if history is None else int(history)
        self.history_keys = tuple(history_keys)

    def training_rows(self, rows: TensorDictBase) -> TensorDictBase:
        """``rows`` with what the loss reads beyond a buffer's columns: chunk labels
        (``horizon``) and observation histories (``history``), each computed from the
        rows' own episodes (``EPISODE``, ``STEP``) unless the rows already carry them
        (rows you labelled yourself are used as they are); ``rows`` itself when neither
        is set."""
        have = set(rows.keys(include_nested=True))
        if self.horizon is not None and not {EXPERT_CHUNK, CHUNK_PAD} <= have:
            rows = add_chunk_labels(rows, self.horizon)
        if self.history is not None:
            for key in self.history_keys:
                if history_key(key) not in have:
                    rows = add_observation_history(
                        rows, self.history, obs_key=key, out_key=history_key(key)
                    )
        return rows

    def fitting_weights(self) -> contextlib.AbstractContextManager:
        """A fit's steps run in it: with an EMA, the trained weights are in the policy
        within and the average without (:meth:`~imitrl.policies.ema.EMA.trained_weights`)."""
        return contextlib.nullcontext() if self.ema is None else self.ema.trained_weights()

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """Every optimizer of the learner by name (saved and restored with it)."""
        return {"opt_pi": self.opt_pi}

    def migrated_state(self, states: dict[str, dict]) -> dict[str, dict]:
        """Saved states (``"learner"``: the weights, and each optimizer's by name) as this
        learner holds them: where a checkpoint of an older imitrl holds what this learner
        no longer carries, it is dropped here; where it lacks a loss's generator state
        (:class:`~imitrl.rng.SavedGenerator`: imitrl up to e0ceebc did not save it), the
        freshly seeded generator is kept, as those versions resumed."""
        saved = states.get("learner")
        if saved is None:
            return states
        own = self.state_dict()
        fresh = {k: own[k] for k in own if k.endswith("_extra_state") and k not in saved}
        return {**states, "learner": {**saved, **fresh}} if fresh else states

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """:meth:`torch.nn.Module.load_state_dict`, after
        :func:`~imitrl.learners.saved_state.check_saved_state`: a value of another kind than
        its weight, NaN or inf once cast, or copies of one shared weight (the policy's and
        its loss's ``actor``) that differ are refused (``ValueError`` naming the key) where
        torch would cast it, or keep whichever copy it loads last."""
        check_saved_state(self, state_dict)
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    @property
    def device(self) -> torch.device:
        """Where the learner computes: its parameters' device (:mod:`imitrl.system.device`)."""
        return module_device(self)

    def placed(self, device: str | torch.device | None) -> Self:
        """The learner moved to ``device`` (``"auto"``, ``"cpu"``, ``"cuda:N"``: see
        :func:`~imitrl.system.device.resolve_device`; None: left where it is); returns
        ``self``. Its optimizers keep their parameters (moved in place), so call it
        before the first step, as the builders' ``device=`` does."""
        if device is None:
            return self
        target = resolve_device(device)
        if target != self.device:
            self.to(target)
        if target.type == "cuda":  # the device's own fast Adam: one fused kernel a step
            for opt in self.optimizers().values():
                if type(opt) is torch.optim.Adam and not opt.state:
                    for group in opt.param_groups:
                        group["fused"] = all(p.is_floating_point() for p in group["params"])
        return self

    def check_observations(self, obs: torch.Tensor) -> None:
        """Raise ``ValueError`` unless ``obs`` is finite (subclasses check shapes too)."""
        if obs.dtype.is_floating_point and not torch.isfinite(obs).all():
            raise ValueError("observations contain NaN or inf")

    def check_env(self, env) -> None:
        """Raise ``ValueError`` (naming both) when the learner cannot act in ``env``.

        The base class knows nothing of its policy's spaces and accepts every env;
        :class:`~imitrl.learners.ActorCritic` compares its observation and action spaces.
        """

    def prepare(self, rows: TensorDictBase) -> None:
        """Before a fit: validate the rows' observations and, the first time, fit the
        normaliser to them (later fits keep the statistics the weights were trained with).

        Only a policy that reads ``OBSERVATION`` needs it: rows of a learner of images
        alone (``in_keys`` a pixel key) may come without one."""
        if keys.OBSERVATION not in self.policy.in_keys:
            return
        obs = rows.get(keys.OBSERVATION, None)
        if obs is None:
            raise ValueError(
                f"the rows lack {keys.OBSERVATION!r}, which the policy reads (its in_keys "
                f"{list(self.policy.in_keys)}; the rows' keys {list(rows.keys())})"
            )
        self.check_observations(obs)
        if self.normalizer is not None and not self.normalizer.is_fitted:
            self.normalizer.fit(obs.reshape(-1, *self.normalizer.shape))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Run the policy on a tensordict (writes ``ACTION``)."""
        return self.policy(tensordict)

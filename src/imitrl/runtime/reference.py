"""The reference stepper: a rollout's step on public TorchRL alone.

Each step is ``td = policy(td)`` then ``out, td = env.step_and_maybe_reset(td)``, exactly
as TorchRL's own ``env.rollout`` steps: any env (batched, parallel, transformed, pixels,
your own ``EnvBase``) and any policy module. The accelerated stepper
(:mod:`imitrl.runtime.fast.stepper`) is tested against this one, digit for digit; it is
what runs on every env the accelerated one does not know, and inside
:func:`imitrl.runtime.paths.reference`.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.runtime.loop import NEXT_KEYS, OPTIONAL_NEXT_KEYS, OPTIONAL_ROW_KEYS, ROW_KEYS, Stepper

__all__ = ["TorchRLStepper"]


class TorchRLStepper(Stepper):
    """``policy(td)`` and ``env.step_and_maybe_reset(td)`` per step (module docstring).

    Args:
        env: any TorchRL env with zero or one batch dimension.
        policy: the module that drives it.
        record: keep each step's row entries for :meth:`trajectory`.
        row_keys: the root entries it keeps (the env's optional ones beside them).
        next_observation: keep ``("next", "observation")`` too.
    """

    def __init__(
        self,
        env: EnvBase,
        policy: TensorDictModuleBase,
        record: bool,
        row_keys: tuple = ROW_KEYS,
        next_observation: bool = False,
    ) -> None:
        self.env, self.policy, self._record = env, policy, record
        self._keys, self._next_observation = tuple(row_keys), next_observation
        self._steps: list[TensorDictBase] = []
        self._row_keys: list | None = None
        self._td: TensorDictBase = TensorDict()  # the env's reset replaces it
        self._out: TensorDictBase | None = None
        self._next: TensorDictBase | None = None

    def reset(self) -> None:
        self._td = self.env.reset()

    def act(self) -> TensorDictBase:
        self._td = self.policy(self._td)
        return self._td

    def step(self) -> tuple[np.ndarray, np.ndarray]:
        if self._record and self._row_keys is None:  # the row keys this env gives
            present = [k for k in OPTIONAL_ROW_KEYS if k in self._td.keys()]
            observed = self.env.observation_spec.keys()
            after = [*NEXT_KEYS, *[k for k in OPTIONAL_NEXT_KEYS if k in observed]]
            if self._next_observation:
                after.append(keys.OBSERVATION)
            self._row_keys = [*self._keys, *present, *[(keys.NEXT, k) for k in after]]
        out, after_reset = self.env.step_and_maybe_reset(self._td)
        self._out, self._next = out, after_reset
        if self._record:
            assert self._row_keys is not None  # set above, at the first step
            self._steps.append(out.select(*self._row_keys))
        nxt = out.get(keys.NEXT)
        reward = nxt.get(keys.REWARD).reshape(-1).cpu().numpy()
        return reward, nxt.get(keys.DONE).reshape(-1).cpu().numpy()

    def advance(self, done: np.ndarray | None) -> None:
        assert self._next is not None  # advance follows a step
        self._td = self._next  # step_and_maybe_reset has reset the finished lanes

    def step_tensordict(self) -> TensorDictBase:
        assert self._out is not None  # asked for after a step
        return self._out

    def trajectory(self) -> TensorDictBase | None:
        if not self._steps:
            return None
        return torch.stack(self._steps, dim=len(self.env.batch_size)).contiguous()

    def clear(self) -> None:
        self._steps = []

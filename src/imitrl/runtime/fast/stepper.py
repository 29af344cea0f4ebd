"""The accelerated stepper: the simulator stepped directly, the policy called on a dict.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

It plays the reference stepper's steps (:class:`imitrl.runtime.reference.TorchRLStepper`)
without TorchRL's per-step TensorDict round trips: the env through its
:class:`~imitrl.runtime.fast.env_steps.DirectSteps` (a plain gymnasium env from
``make_env`` or a ``TabularEnv``), the policy through
:class:`~imitrl.runtime.fast.policy_call.TensorPolicy` on a dict of the root's entries
(what ``step_and_maybe_reset`` leaves there). A step's reward and flags stay numpy values;
a recorded trajectory's ``("next", ...)`` tensors are built once, at its end.

A loop that keeps no tensor (an evaluation) runs a policy replayed module by module
under ``torch.inference_mode`` (a fifth of a small network's call at batch 1). An opaque
module (one run through its own ``forward``) may keep tensors between calls (a chunked
policy's plan, updated in place) that a later rollout outside inference mode could not
update, so it keeps ``no_grad``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.runtime.fast.env_steps import DirectSteps, RawStep
from imitrl.runtime.fast.policy_call import TensorPolicy
from imitrl.runtime.loop import NEXT_KEYS, ROW_KEYS, Stepper

__all__ = ["DirectStepper"]


class DirectStepper(Stepper):
    """``direct`` stepping ``env``'s simulator, ``policy`` called as a :class:`TensorPolicy`.

    Build it inside the rollout's ``set_exploration_type`` (the policy's replay reads the
    exploration type once, when built). ``row_keys``: the root entries recorded;
    ``next_observation``: record ``("next", "observation")`` too.
    """

    def __init__(
        self,
        env: EnvBase,
        direct: DirectSteps,
        policy: TensorDictModuleBase,
        record: bool,
        row_keys: tuple = ROW_KEYS,
        next_observation: bool = False,
    ) -> None:
        self.env, self.policy, self._direct, self._record = env, policy, direct, record
        self.call = TensorPolicy(policy, env.batch_size)
        self._action_key = env.action_key
        self._values: dict = {}
        self._row_keys, self._next_observation = tuple(row_keys), next_observation
        self._columns: dict = {k: [] for k in self._row_keys}
        self._raw: list[RawStep] = []  # the next entries are made tensors once, at the end
        self._last: RawStep | None = None

    @contextlib.contextmanager
    def running(self) -> Iterator[None]:
        if self._record or self.call.opaque:
            yield
            return
        with torch.inference_mode():
            yield

    def reset(self) -> None:
        self._values = dict(self.env.reset().items(include_nested=True, leaves_only=True))

    def act(self) -> dict:
        self.call(self._values)
        return self._values

    def step(self) -> tuple[np.ndarray, np.ndarray]:
        values = self._values
        if self._record:
            for k in self._row_keys:
                self._columns[k].append(values[k])
        self._last = step = self._direct.step_raw(values[self._action_key])
        if self._record:
            self._raw.append(step)
        return step.reward, step.done

    def advance(self, done: np.ndarray | None) -> None:
        if done is None:
            assert self._last is not None  # advance follows a step
            self._values[keys.OBSERVATION] = self._last.observation
        else:
            self._values[keys.OBSERVATION] = self._direct.reset_lanes(done)

    def step_tensordict(self) -> TensorDict:
        step = self._last
        assert step is not None  # asked for after a step
        tensors = dict(zip(NEXT_KEYS, self._direct.step_tensors(step)))
        nxt = {keys.OBSERVATION: step.observation, **tensors}
        return TensorDict({**self._values, keys.NEXT: nxt}, batch_size=self.env.batch_size)

    def trajectory(self) -> TensorDict | None:
        if not self._columns[keys.ACTION]:
            return None
        dim = len(self.env.batch_size)
        stacked = {k: torch.stack(v, dim=dim) for k, v in self._columns.items()}
        nxt = dict(zip(NEXT_KEYS, self._direct.next_tensors(self._raw)))
        if self._next_observation:  # each step's own, before any reset
            nxt[keys.OBSERVATION] = torch.stack([s.observation for s in self._raw], dim=dim)
        return TensorDict(
            {**stacked, keys.NEXT: nxt}, batch_size=stacked[keys.ACTION].shape[: dim + 1]
        )

    def clear(self) -> None:
        self._columns = {k: [] for k in self._row_keys}
        self._raw = []

"""Direct steps: a rollout's env step without TorchRL's per-step TensorDict round trips.

``env.step_and_maybe_reset(td)`` on a ``GymWrapper`` costs several times gymnasium's own
step (issue 16's profile of CartPole: 5.2 s over 6,494 steps, of which ``CartPole.step``
1.1 s): spec encodes, done completion, ``step_mdp``, the reset merge, each through
TensorDicts. For the envs whose TorchRL layer only converts values, :func:`direct_steps`
returns a stepper that steps the simulator underneath and converts the values itself:

* an env built by :func:`~imitrl.envs.make_env` in this process, unchanged since: a
  ``GymWrapper`` around a gymnasium env or a ``SyncVectorEnv(autoreset_mode=DISABLED)``,
  without action repeat, pixels or an info reader, optionally inside the
  ``TransformedEnv`` whose only transform is ``DoubleToFloat``;
* a :class:`~imitrl.envs.TabularEnv` (its own :meth:`~TabularEnv.step_lanes` and
  :meth:`~TabularEnv.reset_lanes`, the code its ``_step``/``_reset`` run).

Anything else (``ParallelEnv``, pixel envs, other transforms, your own ``EnvBase``)
gets None and is stepped through TorchRL. Each conversion below names the TorchRL code
it mirrors, so the values, dtypes and shapes are TorchRL's: rollouts on either path play
the same episodes digit for digit (``tests/test_fast_path.py`` runs both side by side).
The rollout's first reset still goes through TorchRL's ``env.reset()``; a ``set_seed``
too. Do not use the direct path on an env you compiled (``env.compile()``) or gave
post-step hooks: it does not see them (pass ``fast_path=False`` to the rollout).
"""

from __future__ import annotations

import weakref
from abc import ABC, abstractmethod
from typing import NamedTuple

import gymnasium
import numpy as np
import torch
from torchrl.data import Categorical
from torchrl.envs import Compose, DoubleToFloat, EnvBase, GymWrapper, TransformedEnv

from imitrl import keys
from imitrl.compat import wrapped_gym_env
from imitrl.envs.tabular_env import TabularEnv

__all__ = ["DirectSteps", "GymSteps", "Transition", "direct_steps", "register_plain_gym"]

_PLAIN_GYM: weakref.WeakSet[EnvBase] = weakref.WeakSet()
"""the envs ``make_env`` built as a GymWrapper (+ DoubleToFloat) in this process"""


def register_plain_gym(env: EnvBase) -> EnvBase:
    """Mark ``env`` (``make_env``'s in-process GymWrapper, maybe in ``DoubleToFloat``) as
    one :func:`direct_steps` may step directly; returns ``env``."""
    _PLAIN_GYM.add(env)
    return env


class Transition(NamedTuple):
    """One step of every lane, as TorchRL's ``("next", ...)`` entries.

    Shapes: ``observation [*batch, *obs]`` (before any reset), ``reward`` float32
    ``[*batch, 1]``, ``done``/``terminated``/``truncated`` bool ``[*batch, 1]``;
    ``done_lanes`` numpy bool ``[lanes]`` (``done`` for the loop's bookkeeping).
    """

    observation: torch.Tensor
    reward: torch.Tensor
    done: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    done_lanes: np.ndarray


class DirectSteps(ABC):
    """Steps an env's simulator directly (see the module docstring)."""

    batch_size: torch.Size
    """the TorchRL env's batch size (``[]`` or ``[lanes]``)"""

    @abstractmethod
    def step(self, action: torch.Tensor) -> Transition:
        """Step every lane with ``action`` (the env's action spec, ``[*batch, ...]``)."""

    @abstractmethod
    def reset_done(self, step: Transition) -> torch.Tensor:
        """Reset the lanes ``step`` ended (some must have); the observation of every lane
        after it, ``[*batch, *obs]`` (what ``step_and_maybe_reset`` puts at the root)."""


class _TabularSteps(DirectSteps):
    def __init__(self, env: TabularEnv) -> None:
        self.env = env
        self.batch_size = env.batch_size
        self._shape1 = (*env.batch_size, 1)

    def step(self, action: torch.Tensor) -> Transition:
        state, reward, terminated, truncated = self.env.step_lanes(action)
        done = terminated | truncated  # as TabularEnv._step writes it
        return Transition(
            state.reshape(self.batch_size),
            reward.reshape(self._shape1),
            done.reshape(self._shape1),
            terminated.reshape(self._shape1),
            truncated.reshape(self._shape1),
            done.numpy(),
        )

    def reset_done(self, step: Transition) -> torch.Tensor:
        # TorchRL resets with "_reset" = the done flags: the same lanes, the same draws
        lanes = torch.from_numpy(step.done_lanes)
        return self.env.reset_lanes(lanes).reshape(self.batch_size)


class GymSteps(DirectSteps):
    """A gymnasium env, or a ``SyncVectorEnv`` with autoreset DISABLED (``vector``)."""

    def __init__(self, env: EnvBase, base: GymWrapper, gym_env, vector: bool) -> None:
        self.batch_size = env.batch_size
        self._gym, self._vector = gym_env, vector
        self._lanes = int(env.batch_size.numel()) if vector else 1
        obs_spec = base.observation_spec[keys.OBSERVATION]
        self._obs_dtype, self._obs_shape = obs_spec.dtype, obs_spec.shape
        # DoubleToFloat: observations read as float64 are cast to the outer spec's float32
        outer = env.observation_spec[keys.OBSERVATION].dtype
        self._obs_cast = outer if outer != self._obs_dtype else None
        # ... and float32 actions go back to the base env's float64 before the step
        base_action = base.action_spec.dtype
        self._action_cast = base_action if base_action != env.action_spec.dtype else None
        # GymWrapper.read_action: one env's categorical action is passed as a Python int
        self._int_action = not vector and isinstance(base.action_spec, Categorical)
        self._shape1 = (*self.batch_size, 1)

    def lane_envs(self) -> list[gymnasium.Env]:
        """The gymnasium env of each lane (the vector env's copies, or the one env)."""
        return list(self._gym.envs) if self._vector else [self._gym]

    def _observation(self, obs) -> torch.Tensor:
        # TensorSpec._encode_eager, then DoubleToFloat._apply_transform
        if isinstance(obs, list):
            obs = obs[0] if len(obs) == 1 else np.array(obs)
        if isinstance(obs, np.ndarray) and not all(s > 0 for s in obs.strides):
            obs = obs.copy()
        value = torch.as_tensor(obs, dtype=self._obs_dtype)
        if value.shape != self._obs_shape:
            value = value.reshape(self._obs_shape)
        return value if self._obs_cast is None else value.to(self._obs_cast)

    def _reward(self, reward) -> torch.Tensor:
        # GymLikeEnv._step sums 0 + reward; _read_reward_eager encodes it (float32)
        reward = 0 if reward is None else 0 + reward
        if isinstance(reward, int) and reward == 0:
            return torch.zeros(self._shape1, dtype=torch.float32)  # reward_spec.zero()
        if isinstance(reward, np.ndarray) and not all(s > 0 for s in reward.strides):
            reward = reward.copy()
        value = torch.as_tensor(reward, dtype=torch.float32)
        return value if value.shape == self._shape1 else value.reshape(self._shape1)

    def step(self, action: torch.Tensor) -> Transition:
        if self._action_cast is not None:
            action = action.to(self._action_cast)  # DoubleToFloat's inverse
        a = action.detach().cpu().numpy()  # TensorSpec.to_numpy(safe=False)
        if self._int_action:
            a = int(a)
        obs, reward, terminated, truncated, _ = self._gym.step(a)
        done = terminated | truncated  # GymWrapper._output_transform (gymnasium)
        return Transition(
            self._observation(obs), self._reward(reward), *self._flags(done, terminated, truncated)
        )

    def _flags(self, *flags) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray]:
        """done, terminated, truncated ``[*batch, 1]`` and done ``[lanes]`` (numpy)."""
        if all(type(f) is bool for f in flags) or all(
            isinstance(f, np.ndarray) and f.dtype == np.bool_ for f in flags
        ):
            # one tensor for the three: the values and dtype (bool) of TorchRL's three
            stacked = torch.as_tensor(np.array(flags)).reshape(3, *self._shape1)
            done, terminated, truncated = stacked.unbind(0)
        else:
            if isinstance(flags[0], bool):  # GymLikeEnv.read_done
                flags = tuple([f] for f in flags)
            # torch.as_tensor as read_done, reshaped to [*batch, 1] as EnvBase._complete_done
            done, terminated, truncated = (torch.as_tensor(f).reshape(self._shape1) for f in flags)
        return done, terminated, truncated, done.view(-1).numpy()

    def reset_done(self, step: Transition) -> torch.Tensor:
        if self._vector:
            # GymWrapper._replace_reset: reset only the finished lanes; the others
            # keep (and the vector env returns) their observation of this step
            obs, _ = self._gym.reset(options={"reset_mask": step.done_lanes.astype(np.bool_)})
        else:
            obs, _ = self._gym.reset()
        return self._observation(obs)


def _only_double_to_float(env: TransformedEnv) -> bool:
    transform = env.transform
    parts = list(transform) if isinstance(transform, Compose) else [transform]
    return len(parts) == 1 and type(parts[0]) is DoubleToFloat


def direct_steps(env: EnvBase) -> DirectSteps | None:
    """A stepper of ``env``'s simulator (see the module docstring), or None where the
    env must be stepped through TorchRL."""
    if type(env) is TabularEnv:
        return _TabularSteps(env)
    if env not in _PLAIN_GYM:
        return None
    base = env
    if isinstance(env, TransformedEnv):
        if not _only_double_to_float(env):
            return None  # a transform appended since make_env built it
        base = env.base_env
    if not isinstance(base, GymWrapper) or base.wrapper_frame_skip != 1 or base.info_dict_reader:
        return None
    if set(env.observation_spec.keys(True, True)) != {keys.OBSERVATION}:
        return None  # pixels (or another observation) beside the state
    inner = wrapped_gym_env(base)
    if isinstance(inner, gymnasium.vector.VectorEnv):
        if not isinstance(inner, gymnasium.vector.SyncVectorEnv) or (
            inner.autoreset_mode != gymnasium.vector.AutoresetMode.DISABLED
        ):
            return None
        return GymSteps(env, base, inner, vector=True)
    return GymSteps(env, base, inner, vector=False)

"""Direct steps: a rollout's env step without TorchRL's per-step TensorDict round trips.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

``env.step_and_maybe_reset(td)`` on a ``GymWrapper`` costs several times gymnasium's own
step (issue 16's profile of CartPole: 5.2 s over 6,494 steps, of which ``CartPole.step``
1.1 s): spec encodes, done completion, ``step_mdp``, the reset merge, each through
TensorDicts. For the envs whose TorchRL layer only converts values, :func:`direct_steps`
returns a stepper that steps the simulator underneath and converts the values itself:

* an env :func:`~imitrl.envs.make.plain_gym` accepts, built by
  :func:`~imitrl.envs.make_env` in this process and unchanged since: a ``GymWrapper``
  around a gymnasium env or a ``SyncVectorEnv(autoreset_mode=DISABLED)``, without action
  repeat, pixels or an info reader, optionally inside the ``TransformedEnv`` whose only
  transform is ``DoubleToFloat``;
* a :class:`~imitrl.envs.TabularEnv` (its own :meth:`~TabularEnv.step_lanes` and
  :meth:`~TabularEnv.reset_lanes`, the code its ``_step``/``_reset`` run).

A step leaves the reward and the flags as numpy values (:class:`RawStep`): a return
needs no tensor, and a trajectory's ``("next", ...)`` tensors are built once, at its end
(:meth:`DirectSteps.next_tensors`), with TorchRL's values, dtypes and shapes; on
CartPole a tensor per value and step cost more than gymnasium's own step.

Anything else (``ParallelEnv``, pixel envs, other transforms, your own ``EnvBase``)
gets None and is stepped through TorchRL. Each conversion below names the TorchRL code
it mirrors, so the values, dtypes and shapes are TorchRL's: rollouts on either path play
the same episodes digit for digit (``tests/runtime/test_paths.py`` runs both side by side).
The rollout's first reset still goes through TorchRL's ``env.reset()``; a ``set_seed``
too. Do not use the direct path on an env you compiled (``env.compile()``) or gave
post-step hooks: it does not see them (run the rollout inside
``imitrl.runtime.paths.reference("stepper")``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import NamedTuple

import gymnasium
import numpy as np
import torch
from torchrl.data import Categorical
from torchrl.envs import EnvBase, GymWrapper

from imitrl import keys
from imitrl.envs.make import plain_gym
from imitrl.envs.tabular_env import TabularEnv

__all__ = [
    "DirectSteps",
    "GymSteps",
    "RawStep",
    "direct_steps",
]


class RawStep(NamedTuple):
    """One step of every lane with the scalars left as numpy ``[lanes]`` arrays: what a
    loop that only adds up returns, or stacks a whole trajectory's flags at its end, needs
    (a torch tensor per value and step costs more than gymnasium's own step on small envs).

    ``reward`` float32 (the values TorchRL's float32 reward spec holds), ``terminated``,
    ``truncated``, ``done`` bool; ``observation`` ``[*batch, *obs]``, before any reset.
    """

    observation: torch.Tensor
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    done: np.ndarray


class DirectSteps(ABC):
    """Steps an env's simulator directly (see the module docstring)."""

    batch_size: torch.Size
    """the TorchRL env's batch size (``[]`` or ``[lanes]``)"""

    @abstractmethod
    def step_raw(self, action: torch.Tensor) -> RawStep:
        """Step every lane with ``action`` (the env's action spec, ``[*batch, ...]``)."""

    @abstractmethod
    def reset_lanes(self, done: np.ndarray) -> torch.Tensor:
        """Reset the lanes of the bool mask ``done`` ``[lanes]`` (some must be set); the
        observation of every lane after it, ``[*batch, *obs]`` (what
        ``step_and_maybe_reset`` puts at the root)."""

    def next_tensors(self, steps: Sequence[RawStep]) -> tuple[torch.Tensor, ...]:
        """``reward, done, terminated, truncated`` of a trajectory's ``steps`` (in order),
        each ``[*batch, T, 1]``: the values, dtypes and shapes of TorchRL's entries,
        stacked as a rollout stacks them."""
        return self._tensors(steps, (*self.batch_size, len(steps), 1))

    def step_tensors(self, step: RawStep) -> tuple[torch.Tensor, ...]:
        """:meth:`next_tensors` of one step, each ``[*batch, 1]``."""
        return self._tensors([step], (*self.batch_size, 1))

    @staticmethod
    def _tensors(steps: Sequence[RawStep], shape: tuple[int, ...]) -> tuple[torch.Tensor, ...]:
        fields = ("reward", "done", "terminated", "truncated")
        # [lanes, T] per field: lanes first, as TorchRL stacks a batched env's steps
        return tuple(
            torch.from_numpy(np.stack([getattr(s, f) for s in steps], axis=-1)).reshape(shape)
            for f in fields
        )


class _TabularSteps(DirectSteps):
    def __init__(self, env: TabularEnv) -> None:
        self.env = env
        self.batch_size = env.batch_size

    def step_raw(self, action: torch.Tensor) -> RawStep:
        state, reward, terminated, truncated = self.env.step_lanes(action)
        ended, cut = terminated.numpy(), truncated.numpy()
        return RawStep(
            state.reshape(self.batch_size),
            reward.numpy(),
            ended,
            cut,
            ended | cut,  # as TabularEnv._step writes it
        )

    def reset_lanes(self, done: np.ndarray) -> torch.Tensor:
        # TorchRL resets with "_reset" = the done flags: the same lanes, the same draws
        return self.env.reset_lanes(torch.from_numpy(done)).reshape(self.batch_size)


_TRUE, _FALSE = np.ones(1, dtype=np.bool_), np.zeros(1, dtype=np.bool_)
_TRUE.flags.writeable = _FALSE.flags.writeable = False  # shared by every step: read-only

_NUMPY_DTYPES = {
    torch.float32: np.float32,
    torch.float64: np.float64,
    torch.int64: np.int64,
    torch.int32: np.int32,
    torch.uint8: np.uint8,
    torch.bool: np.bool_,
}


class GymSteps(DirectSteps):
    """A gymnasium env, or a ``SyncVectorEnv`` with autoreset DISABLED (``vector``)."""

    def __init__(self, env: EnvBase, base: GymWrapper, gym_env, vector: bool) -> None:
        self.batch_size = env.batch_size
        self._gym, self._vector = gym_env, vector
        self._lanes = int(env.batch_size.numel()) if vector else 1
        obs_spec = base.observation_spec[keys.OBSERVATION]
        self._obs_dtype, self._obs_shape = obs_spec.dtype, obs_spec.shape
        self._obs_numpy = _NUMPY_DTYPES.get(obs_spec.dtype)
        # DoubleToFloat: observations read as float64 are cast to the outer spec's float32
        outer = env.observation_spec[keys.OBSERVATION].dtype
        self._obs_cast = outer if outer != self._obs_dtype else None
        # ... and float32 actions go back to the base env's float64 before the step
        base_action = base.action_spec.dtype
        self._action_cast = base_action if base_action != env.action_spec.dtype else None
        # GymWrapper.read_action: one env's categorical action is passed as a Python int
        self._int_action = not vector and isinstance(base.action_spec, Categorical)

    def lane_envs(self) -> list[gymnasium.Env]:
        """The gymnasium env of each lane (the vector env's copies, or the one env)."""
        return list(self._gym.envs) if self._vector else [self._gym]

    def _observation(self, obs) -> torch.Tensor:
        # TensorSpec._encode_eager, then DoubleToFloat._apply_transform
        if (
            type(obs) is np.ndarray
            and obs.dtype == self._obs_numpy
            and obs.shape == self._obs_shape
            and obs.flags.c_contiguous
        ):
            # torch.as_tensor of an array of the spec's dtype shares its memory, as this does
            value = torch.from_numpy(obs)
            return value if self._obs_cast is None else value.to(self._obs_cast)
        if isinstance(obs, list):
            obs = obs[0] if len(obs) == 1 else np.array(obs)
        if isinstance(obs, np.ndarray) and not all(s > 0 for s in obs.strides):
            obs = obs.copy()
        value = torch.as_tensor(obs, dtype=self._obs_dtype)
        if value.shape != self._obs_shape:
            value = value.reshape(self._obs_shape)
        return value if self._obs_cast is None else value.to(self._obs_cast)

    def _reward(self, reward) -> np.ndarray:
        # GymLikeEnv._step sums 0 + reward; _read_reward_eager encodes it as float32 (the
        # rounding of np.float32 is torch's: to nearest)
        reward = 0 if reward is None else 0 + reward
        # a copy: a trajectory keeps every step's values until its end
        return np.array(reward, dtype=np.float32).reshape(self._lanes)

    def _flag(self, flag) -> np.ndarray:
        # GymLikeEnv.read_done, then the bool done spec (a flag gymnasium gives as bool,
        # numpy bool or an array of them); one env's Python bool: a shared read-only array
        if flag is True or flag is False:
            return _TRUE if flag else _FALSE
        return np.array(flag, dtype=np.bool_).reshape(self._lanes)  # a copy, as the reward

    def step_raw(self, action: torch.Tensor) -> RawStep:
        if self._action_cast is not None:
            action = action.to(self._action_cast)  # DoubleToFloat's inverse
        if action.requires_grad or not action.is_cpu:
            action = action.detach().cpu()
        a = action.numpy()  # TensorSpec.to_numpy(safe=False)
        obs, reward, terminated, truncated, _ = self._gym.step(int(a) if self._int_action else a)
        terminated, truncated = self._flag(terminated), self._flag(truncated)
        # GymWrapper._output_transform (gymnasium): done = terminated | truncated
        done = _FALSE if terminated is _FALSE and truncated is _FALSE else terminated | truncated
        return RawStep(self._observation(obs), self._reward(reward), terminated, truncated, done)

    def reset_lanes(self, done: np.ndarray) -> torch.Tensor:
        if self._vector:
            # GymWrapper._replace_reset: reset only the finished lanes; the others
            # keep (and the vector env returns) their observation of this step
            obs, _ = self._gym.reset(options={"reset_mask": done.astype(np.bool_)})
        else:
            obs, _ = self._gym.reset()
        return self._observation(obs)


def direct_steps(env: EnvBase) -> DirectSteps | None:
    """A stepper of ``env``'s simulator (see the module docstring), or None where the
    env must be stepped through TorchRL."""
    if type(env) is TabularEnv:
        return _TabularSteps(env)
    plain = plain_gym(env)  # what make_env built, unchanged
    if plain is None:
        return None
    vector = isinstance(plain.inner, gymnasium.vector.VectorEnv)
    return GymSteps(env, plain.base, plain.inner, vector=vector)

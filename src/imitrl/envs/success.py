"""``info["success"]`` made a flag TorchRL reads: a bool, set from the first success on.

Manipulation suites (Meta-World, robosuite, LIBERO) report success per step in
``info["success"]``, often as a float; Meta-World's evaluation counts an episode a
success when the flag is set at any step of it. :class:`SuccessInfo` turns the flag into
a numpy bool that stays set for the rest of the episode, optionally ends the episode at
the first success, and ``make_env`` (``success=True``, on by default for the
``metaworld/`` ids) reads it into the step's ``("next", "success")``: the flag at an
episode's last step is then its "at any step" success, whatever ends the episode.
:func:`~imitrl.evaluation.evaluate` reports its rate, with a Wilson interval.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import gymnasium
import numpy as np

if TYPE_CHECKING:  # the wrapper needs neither: make_env's workers import it cheaply
    import torch
    from tensordict import TensorDictBase

__all__ = ["SUCCESS", "SuccessInfo", "reads_success", "reported_success", "success_reader"]

SUCCESS = "success"
"""the info key (and the TorchRL key under ``"next"``)"""


class SuccessInfo(gymnasium.Wrapper):
    """``info["success"]`` as a bool set from the episode's first success on.

    Args:
        env: a gymnasium env whose ``step`` info holds ``"success"`` (a number or a bool).
        terminate: end the episode (``terminated=True``) at its first success.

    Raises:
        ValueError: (at the first step) the env's info has no ``"success"``.
    """

    def __init__(self, env: gymnasium.Env, *, terminate: bool = False) -> None:
        super().__init__(env)
        self.terminate = bool(terminate)
        self._reached = False

    def reset(self, **kwargs):
        self._reached = False
        # no flag in the reset info: a vector env's partial reset would fill the other
        # lanes' entries with None (an object array); TorchRL writes the spec's zero
        return self.env.reset(**kwargs)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if SUCCESS not in info:
            raise ValueError(
                f"{self.env.spec.id if self.env.spec else type(self.env).__name__} gave no "
                "info['success'] at a step: read success only from envs that report it"
            )
        self._reached = self._reached or bool(info[SUCCESS])
        info[SUCCESS] = np.bool_(self._reached)
        if self.terminate and self._reached:
            terminated = True
        return obs, reward, terminated, truncated, info


def reads_success(env: object) -> bool:
    """Whether ``env`` (or an env it wraps) is a :class:`SuccessInfo`."""
    while isinstance(env, gymnasium.Wrapper):
        if isinstance(env, SuccessInfo):
            return True
        env = env.env
    return False


def success_reader(batch_size: tuple[int, ...] = ()):
    """TorchRL's info reader of the flag: ``("next", "success")``, bool ``[*batch_size]``
    (one per lane of a vectorised env)."""
    import torch
    from torchrl.data import Composite, Unbounded
    from torchrl.envs.libs.gym import default_info_dict_reader

    spec = Composite({SUCCESS: Unbounded(shape=batch_size, dtype=torch.bool)}, shape=batch_size)
    return default_info_dict_reader([SUCCESS], spec=spec)


def reported_success(out: TensorDictBase) -> torch.Tensor:
    """The env's own flag at an episode's last step, ``[lanes]`` bool: with
    :class:`SuccessInfo` it is set from the episode's first success on, so this is
    Meta-World's "success at any step" (a ``success_fn`` of ``episode_returns``)."""
    return out.get(("next", SUCCESS)).reshape(-1)

"""A simulator's state taken and put back in place: what lets an expert plan from a
visited state (chunk-aware DAgger) without disturbing the episode being played.

:meth:`Snapshot.take` records everything a step can read or change, layer by layer:

* a TorchRL env wrapping a gymnasium env (``make_env``'s; a ``TransformedEnv`` over it):
  each gymnasium layer, wrappers down to the raw env (``TimeLimit``'s step count, a
  classic-control env's ``state``, a generator's state); MuJoCo's ``MjData`` (its whole
  integration state through ``mj_getState``, and its other fixed-size arrays, which a
  step can read before it integrates: a body's position, a site's);
* a TorchRL env of its own (imitrl's ``TabularEnv``, the steering tasks): its tensors,
  arrays, generators and plain values;
* a ``SyncVectorEnv`` (lanes): the vector env's own bookkeeping and every copy's layers.

:meth:`Snapshot.restore` puts each value back: an array in place where the attribute
still holds the same array (Meta-World keeps views into ``MjData``: the pads' first
positions alias the bodies' positions), otherwise bound anew; MuJoCo through
``mj_setState`` and the arrays. Restored, the env steps as it would have: the next steps
give the same observations, rewards and flags, bit for bit (``tests/envs/test_snapshot.py``:
classic control, MuJoCo locomotion, all 50 Meta-World tasks, the tabular and steering
tasks). Envs in other processes (``AsyncVectorEnv``, TorchRL's ``ParallelEnv``) are
refused: their state is not here to take.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import gymnasium
import numpy as np
import torch
from torchrl.envs import EnvBase, GymWrapper, TransformedEnv

from imitrl.compat import wrapped_gym_env

__all__ = ["Snapshot"]

_PLAIN = (int, float, bool, str, type(None), np.integer, np.floating, np.bool_)


@dataclass
class Snapshot:
    """The state of one env, taken by :meth:`take`, put back by :meth:`restore`."""

    layers: list[tuple[object, dict[str, tuple]]] = field(default_factory=list)

    @classmethod
    def take(cls, env: EnvBase) -> Snapshot:
        """Record ``env``'s state (module docstring); ValueError naming the env where it
        cannot be taken."""
        return cls([(obj, _capture(obj)) for obj in _holders(env)])

    def restore(self) -> None:
        """Put every recorded value back (module docstring)."""
        for obj, saved in self.layers:
            for name, entry in saved.items():
                _put(obj, name, entry)


def _holders(env: EnvBase) -> list[object]:
    """The objects whose attributes hold ``env``'s state."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    if isinstance(env, GymWrapper):
        inner = wrapped_gym_env(env)
        if isinstance(inner, gymnasium.vector.SyncVectorEnv):
            return [inner, *[layer for sub in inner.envs for layer in _gym_layers(sub)]]
        if isinstance(inner, gymnasium.vector.VectorEnv):
            raise ValueError(
                f"{type(inner).__name__} steps its envs in other processes: their state cannot "
                "be taken here (make the env with its lanes in this process)"
            )
        return _gym_layers(inner)
    if type(env).__module__.startswith("torchrl."):
        raise ValueError(
            f"the state of a TorchRL {type(env).__name__} cannot be taken (a gymnasium env "
            "through make_env, or an env of imitrl's own, can)"
        )
    return [env]


def _gym_layers(env: object) -> list[object]:
    out = [env]
    while isinstance(out[-1], gymnasium.Wrapper):
        out.append(out[-1].env)
    return out


def _capture(obj: object) -> dict[str, tuple]:
    saved: dict[str, tuple] = {}
    for name, value in vars(obj).items():
        if isinstance(value, gymnasium.Env | gymnasium.vector.VectorEnv):
            continue  # a layer of its own
        entry = _entry(obj, value)
        if entry is not None:
            saved[name] = entry
    return saved


def _entry(obj: object, value: Any) -> tuple | None:
    module = type(value).__module__
    if module.startswith("mujoco"):
        return _mujoco(obj, value) if type(value).__name__ == "MjData" else None
    if isinstance(value, torch.Generator):
        return ("generator", value, value.get_state())
    if isinstance(value, torch.Tensor):
        return ("array", value, value.clone())
    if isinstance(value, np.ndarray):
        return ("array", value, value.copy())
    if isinstance(value, (np.random.Generator, *_PLAIN)):
        return ("value", copy.deepcopy(value))
    if isinstance(value, tuple | list | dict) and _plain_tree(value):
        return ("value", copy.deepcopy(value))
    return None  # specs, spaces, renderers, models: what a step does not change


def _plain_tree(value: Any) -> bool:
    if isinstance(value, tuple | list):
        return all(_plain_tree(v) for v in value)
    if isinstance(value, dict):
        return all(_plain_tree(v) for v in value.values())
    return isinstance(value, (*_PLAIN, np.ndarray, torch.Tensor, np.random.Generator))


def _mujoco(obj: object, data: Any) -> tuple:
    import mujoco

    model = getattr(obj, "model", None)
    if model is None:
        raise ValueError(f"{type(obj).__name__} holds MjData without its model")
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    arrays = {}
    for name in dir(data):
        if name.startswith("_"):
            continue
        array = getattr(data, name, None)
        if isinstance(array, np.ndarray) and array.size and array.flags.writeable:
            arrays[name] = array.copy()
    return ("mujoco", data, (model, state, arrays))


def _put(obj: object, name: str, entry: tuple) -> None:
    kind = entry[0]
    if kind == "value":
        setattr(obj, name, copy.deepcopy(entry[1]))
    elif kind == "generator":
        entry[1].set_state(entry[2])
        setattr(obj, name, entry[1])
    elif kind == "array":
        held: Any = entry[1]
        saved: Any = entry[2]
        same = getattr(obj, name, None) is held
        if same and held.shape == saved.shape:
            held[...] = saved  # in place: views into it (and their holders) follow
        else:
            setattr(obj, name, saved.clone() if isinstance(saved, torch.Tensor) else saved.copy())
    else:  # mujoco
        import mujoco

        data, (model, state, arrays) = entry[1], entry[2]
        setattr(obj, name, data)
        mujoco.mj_setState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
        for field_name, saved in arrays.items():
            target = getattr(data, field_name)
            if target.shape == saved.shape:  # sized by the contacts: recomputed by a step
                target[...] = saved

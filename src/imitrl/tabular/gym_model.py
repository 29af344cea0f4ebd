"""Reading a gymnasium toy-text model (``env.unwrapped.P``) into ordered outcome lists.

gymnasium's model is a dict ``s -> a -> [(prob, next_state, reward, terminated), ...]``;
:meth:`TabularMDP.from_gym` builds its MDP from what these functions return: the
validated lists, in the env's own order, and the terminal states they imply.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from imitrl.tabular.validation import ROW_TOL

__all__ = ["make_env", "read_gym_model", "terminal_states"]


def make_env(env: str | gym.Env, make_kwargs: Mapping[str, Any] | None) -> gym.Env:
    """``gym.make(env, **make_kwargs)`` for an id, ``env`` itself for an instance.

    Raises:
        ValueError: unknown or unbuildable id, rejected arguments, or ``make_kwargs``
            given with an env instance.
    """
    if isinstance(env, str):
        env_id = env
        try:
            return gym.make(env_id, **dict(make_kwargs or {}))
        except gym.error.Error as err:
            raise ValueError(f"unknown or unbuildable gymnasium env id {env_id!r}: {err}") from err
        except TypeError as err:
            raise ValueError(
                f"gymnasium env {env_id!r} rejected the arguments {dict(make_kwargs or {})}: {err}"
            ) from err
    if make_kwargs:
        raise ValueError("make_kwargs only applies when env is given as an id string")
    return env


def read_gym_model(
    model: Mapping, S: int, A: int, name: str
) -> list[list[list[tuple[float, int, float, bool]]]]:
    """``lists[s][a]``: the checked outcomes ``(prob, next_state, reward, terminated)``, in order.

    Raises:
        ValueError: a missing state or action, a malformed entry, a next state outside
            ``[0, S)``, a negative or non-finite probability, a non-finite reward, or
            outcome probabilities not summing to 1 (within ``ROW_TOL``).
    """
    lists: list[list[list[tuple[float, int, float, bool]]]] = []
    for s in range(S):
        if s not in model or not isinstance(model[s], Mapping):
            raise ValueError(
                f"env {name!r}: model P has no entry for state {s} (expected {S} states)"
            )
        row = []
        for a in range(A):
            outs = model[s].get(a)
            if not outs:
                raise ValueError(f"env {name!r}: model P[{s}] has no outcome list for action {a}")
            parsed = []
            for out in outs:
                if len(out) != 4:
                    raise ValueError(
                        f"env {name!r}: P[{s}][{a}] entry {out!r} is not (prob, next_state, reward, terminated)"
                    )
                p, t, rew, term = out
                p, rew = float(p), float(rew)
                if not (0 <= int(t) < S) or int(t) != t:
                    raise ValueError(f"env {name!r}: P[{s}][{a}] next state {t!r} outside [0, {S})")
                if not np.isfinite(p) or p < 0:
                    raise ValueError(
                        f"env {name!r}: P[{s}][{a}] has a negative or non-finite probability {p!r}"
                    )
                if not np.isfinite(rew):
                    raise ValueError(f"env {name!r}: P[{s}][{a}] has a non-finite reward {rew!r}")
                parsed.append((p, int(t), rew, bool(term)))
            total = sum(o[0] for o in parsed)
            if abs(total - 1.0) > ROW_TOL:
                raise ValueError(
                    f"env {name!r}: outcome probabilities of P[{s}][{a}] sum to {total:.12g}, not 1"
                )
            row.append(parsed)
        lists.append(row)
    return lists


def terminal_states(
    next_state: np.ndarray,
    prob: np.ndarray,
    terminated: np.ndarray,
    size: np.ndarray,
    initial: np.ndarray,
    name: str,
) -> np.ndarray:
    """States entered by a ``terminated`` outcome, over transitions an episode can take.

    Only states reachable from the initial support (without passing a terminating
    transition) are expanded: gymnasium models also list transitions out of states
    no episode visits (Taxi's post-drop-off states), which never happen.

    Raises:
        ValueError: a reachable state is entered both with and without
            ``terminated`` (termination would depend on more than the next state).
    """
    S = next_state.shape[0]
    real = np.arange(next_state.shape[-1])[None, None, :] < size[:, :, None]
    live = real & (prob > 0)
    term_into = np.zeros(S, dtype=bool)
    cont_into = np.zeros(S, dtype=bool)
    seen = initial > 0
    frontier = np.flatnonzero(seen)
    while frontier.size:
        nxt = next_state[frontier]  # [F, A, K]
        ok = live[frontier]
        term = terminated[frontier]
        term_into[nxt[ok & term]] = True
        cont = nxt[ok & ~term]
        cont_into[cont] = True
        new = np.zeros(S, dtype=bool)
        new[cont] = True
        new &= ~seen
        seen |= new
        frontier = np.flatnonzero(new)
    clash = term_into & cont_into
    if clash.any():
        raise ValueError(
            f"env {name!r}: termination is not a function of the next state: state "
            f"{int(np.flatnonzero(clash)[0])} is entered both with and without `terminated`"
        )
    return term_into

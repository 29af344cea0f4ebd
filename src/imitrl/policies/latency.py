"""Action chunks under inference latency: a query answered ``d`` control steps later.

A chunked policy (:class:`~imitrl.policies.chunking.ChunkedPolicy`) acts as if its network
answered at once. On a robot, a query takes time: with an inference delay of ``d`` steps the
chunk planned from the observation at step ``t`` is ready at step ``t + d``, and the robot
must do something meanwhile. :class:`DelayedChunkPolicy` simulates that delay inside the
rollout loop (every rollout, evaluation and DAgger round runs it unchanged) and executes the
chunks in one of four ways (:data:`MODES`), each chunk ``H`` actions long, ``s`` of them
executed per chunk (the execution horizon):

* ``sync``: the robot stops while it waits. Every ``s`` steps it queries, holds still for
  ``d`` steps (the ``hold`` action: zero, within the bounds) and then executes the chunk
  from its first action; the world does not wait (a pendulum keeps falling, a moving point
  keeps moving).
* ``naive``: asynchronous execution. The next query starts ``d`` steps before the current
  chunk's ``s`` actions run out, from the observation then; meanwhile the current chunk goes
  on; when the new chunk arrives it takes over at its action ``d`` (its first ``d`` are past).
  Consecutive chunks need not agree, so the action can jump where one takes over.
* ``ensemble``: ACT's temporal ensembling with the delay: a query every step; the action at
  step ``t`` averages every chunk that has *arrived* (queried at ``t' <= t - d``, within the
  last ``H`` steps) with ACT's weights ``exp(-m i)``, ``i = 0`` the oldest.
* ``rtc``: real-time chunking (Black et al. 2025): the schedule of ``naive``, but the new
  chunk is sampled as an inpainting of the current one: its first ``d`` actions (executed
  from the current chunk while it is computed) are frozen to the current chunk's, the next
  ones are pulled towards it with weights that decay exponentially to 0 at ``H - s``, the
  rest are free (:func:`rtc_weights`). It needs a generative network that can be guided, a
  flow or a diffusion policy (``network.inpaint(td, target, weights, guidance)``:
  :meth:`~imitrl.learners.flow.policy.FlowPolicy.inpaint`).

The first chunk of an episode is ready at once (a robot starts moving once its first chunk
is there). ``naive`` and ``rtc`` need ``d <= s <= H - d`` (the new chunk arrives before the
current one runs out); ``ensemble`` needs ``d < H``. With ``d = 0``, ``naive`` and ``sync``
execute exactly what the receding horizon of a
:class:`~imitrl.policies.chunking.ChunkedPolicy` with ``execute = s`` executes, and
``ensemble`` what its temporal ensembling does (``tests/policies/test_latency.py``);
``rtc`` keeps the receding horizon's schedule but still pulls each new chunk towards the
current one's actions it has not executed (no action is frozen, the soft weights remain),
so its actions differ: a smoother hand-over, not the same policy.

Writes ``ACTION`` and :data:`CHUNK_SWITCH` (a new chunk took over at this step; every step of
``ensemble`` after the first ``d``): where the action may jump, which a jerk measured at
chunk boundaries reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded

from imitrl import keys
from imitrl.checks import finite_at_least, whole
from imitrl.data.chunks import IS_INIT
from imitrl.policies.chunking import ACT_ENSEMBLE_M, ChunkedPolicy, reset_lanes

__all__ = [
    "CHUNK_SWITCH",
    "MODES",
    "RTC_GUIDANCE",
    "DelayedChunkPolicy",
    "Latency",
    "hold_action",
    "rtc_weights",
]

MODES = ("sync", "naive", "ensemble", "rtc")
CHUNK_SWITCH = "chunk_switch"
"""bool ``[*B]``: a new chunk took over at this step"""
RTC_GUIDANCE = 5.0
"""real-time chunking's largest guidance weight, beta (Black et al. 2025 use 5)"""


@dataclass(frozen=True)
class Latency:
    """An inference delay and how a chunked policy executes its chunks under it."""

    delay: int = 0
    """``d``: control steps between a query and its chunk"""
    mode: str = "naive"
    """one of :data:`MODES` (module docstring)"""
    execute: int | None = None
    """``s``: actions executed per chunk (not ``ensemble``); None: the policy's own (its
    receding horizon's ``execute``; ``H // 2`` for a policy that ensembles)"""
    ensemble: float | None = None
    """``m`` of ``ensemble``'s weights; None: the policy's own, else ACT's"""
    guidance: float = RTC_GUIDANCE
    """``rtc``'s largest guidance weight"""

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"Latency.mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if not whole(self.delay, 0):
            raise ValueError(
                f"Latency.delay must be a whole number of steps >= 0, got {self.delay!r}"
            )
        if self.execute is not None and not whole(self.execute, 1):
            raise ValueError(f"Latency.execute must be a positive integer, got {self.execute!r}")
        if self.ensemble is not None and not finite_at_least(self.ensemble, 0):
            raise ValueError(f"Latency.ensemble (m) must be finite and >= 0, got {self.ensemble!r}")
        if not self.guidance >= 0 or not math.isfinite(self.guidance):
            raise ValueError(f"Latency.guidance must be finite and >= 0, got {self.guidance!r}")


def hold_action(spec: Bounded) -> torch.Tensor:
    """``[m]`` the action that holds a robot still while it waits (``sync``): zero, moved into
    the bounds of ``spec``."""
    low, high = spec.space.low.float(), spec.space.high.float()
    return torch.zeros_like(low).clamp(low, high)


def rtc_weights(horizon: int, delay: int, executed: torch.Tensor) -> torch.Tensor:
    """``[L, H]`` real-time chunking's soft mask (Black et al. 2025, eq. 5) for lanes whose
    current chunk has ``executed`` ``[L]`` actions behind it when the query starts: 1 for the
    first ``d`` actions (frozen), ``c (e^c - 1) / (e - 1)`` with ``c = (H - e - i) / (H - e - d
    + 1)`` for ``d <= i < H - e``, 0 from ``H - e`` on (the current chunk has no action there)."""
    i = torch.arange(int(horizon), device=executed.device)[None, :].double()
    limit = (int(horizon) - executed)[:, None].double()
    c = (limit - i) / (limit - delay + 1)
    decay = c * (torch.exp(c) - 1) / (math.e - 1)
    w = torch.where(i < delay, 1.0, torch.where(i < limit, decay, 0.0))
    return w.float()


class DelayedChunkPolicy(TensorDictModuleBase):
    """``OBSERVATION, is_init -> ACTION, CHUNK_SWITCH``: a chunk network's actions under an
    inference delay (module docstring).

    Args:
        network: writes a flat ``ACTION`` ``[*B, H * m]`` from the inputs it reads (with
            ``inpaint`` for ``rtc``).
        action_dim: ``m``.
        horizon: ``H``.
        latency: the delay and the execution mode.
        hold: ``[m]`` what ``sync`` executes while it waits (:func:`hold_action`).
        hold_noise: draw a generative network's starting noise once per episode and lane,
            as :class:`~imitrl.policies.chunking.ChunkExecution` does.
    """

    def __init__(
        self,
        network: TensorDictModuleBase,
        action_dim: int,
        horizon: int,
        latency: Latency,
        *,
        hold: torch.Tensor | None = None,
        hold_noise: bool = False,
    ) -> None:
        super().__init__()
        H, d, mode = int(horizon), int(latency.delay), latency.mode
        s = H // 2 if latency.execute is None else int(latency.execute)
        _check(network, H, d, s, latency, hold, hold_noise)
        self.network, self.action_dim, self.horizon = network, int(action_dim), H
        self.latency, self.delay, self.execute, self.mode = latency, d, s, mode
        m = latency.ensemble
        self.ensemble = ACT_ENSEMBLE_M if m is None else float(m)
        self.hold_noise = bool(hold_noise)
        self.in_keys = [*network.in_keys, IS_INIT]
        self.out_keys = [keys.ACTION, CHUNK_SWITCH]
        self.register_buffer("hold", None if hold is None else hold.float().clone())
        self._state: dict[str, torch.Tensor] = {}

    @classmethod
    def wrapping(
        cls, policy: ChunkedPolicy, latency: Latency, hold: torch.Tensor | None = None
    ) -> DelayedChunkPolicy:
        """The same network as ``policy`` (its ``H``, its held noise; its ``execute`` or
        ensembling ``m`` where ``latency`` leaves them to it) under ``latency``."""
        ex = policy.execution
        if policy.history is not None:
            raise ValueError(
                "a policy that reads an observation history has no latency mode yet: its "
                "history would need the observations of the steps the delay skips"
            )
        execute = latency.execute if latency.execute is not None else ex.execute
        m = latency.ensemble if latency.ensemble is not None else ex.ensemble
        latency = replace(latency, execute=execute, ensemble=m)
        return cls(policy.network, policy.action_dim, ex.horizon, latency, hold=hold,
                   hold_noise=ex.hold_noise)  # fmt: skip

    # ------------------------------------------------------------------ queries
    def _inputs(self, td: TensorDictBase, lanes: torch.Tensor) -> TensorDictBase:
        """The network's inputs for the lanes ``lanes`` (a mask), with their held noise."""
        sub = td[lanes].select(*self.network.in_keys, strict=True)
        noise = self._state.get("noise")
        if noise is not None:
            sub.set(keys.POLICY_NOISE, noise[lanes])
        return sub

    def _query(self, td: TensorDictBase, lanes: torch.Tensor) -> torch.Tensor:
        """``[n, H, m]`` the network's chunks for the lanes ``lanes`` (a mask)."""
        flat = self.network(self._inputs(td, lanes)).get(keys.ACTION)
        return flat.unflatten(-1, (self.horizon, self.action_dim))

    def _inpaint(self, td: TensorDictBase, lanes: torch.Tensor) -> torch.Tensor:
        """``rtc``: the lanes' new chunks guided by their current ones, from the action
        about to execute on (what the delay executes, then the overlap)."""
        st, H = self._state, self.horizon
        active, age = st["active"][lanes], st["age"][lanes]
        index = (age[:, None] + torch.arange(H, device=age.device)[None, :]).clamp(max=H - 1)
        target = torch.gather(active, 1, index[..., None].expand(-1, -1, self.action_dim))
        w = rtc_weights(H, self.delay, age).to(active.device)
        w = w[..., None].expand(-1, -1, self.action_dim)
        flat = self.network.inpaint(
            self._inputs(td, lanes), target.flatten(-2), w.flatten(-2), self.latency.guidance
        )
        return flat.unflatten(-1, (H, self.action_dim))

    # ------------------------------------------------------------------ steps
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        lanes = batch.numel()
        init = reset_lanes(tensordict)
        if self._state.get("age") is None or self._state["age"].shape[0] != lanes:
            if not bool(init.all()):
                raise ValueError("a chunked policy's first call must follow a reset of every lane")
            self._reset(lanes, init.device)
        if self.hold_noise and bool(init.any()):
            draw = self.network.draw_noise(int(init.sum()))
            noise = self._state.get("noise")
            if noise is None or noise.shape != (lanes, draw.shape[-1]):
                noise = torch.zeros(lanes, draw.shape[-1], dtype=draw.dtype, device=draw.device)
            noise[init.to(draw.device)] = draw
            self._state["noise"] = noise
        td = tensordict.reshape(lanes) if len(batch) != 1 else tensordict
        if self.mode == "ensemble":
            action, switch = self._ensemble_step(td, init)
        elif self.mode == "sync":
            action, switch = self._sync_step(td, init)
        else:
            action, switch = self._async_step(td, init)
        tensordict.set(keys.ACTION, action.reshape(*batch, self.action_dim))
        tensordict.set(CHUNK_SWITCH, switch.reshape(batch))
        return tensordict

    def _reset(self, lanes: int, device: torch.device) -> None:
        H, m = self.horizon, self.action_dim

        def zeros(*shape, dtype=torch.float32):
            return torch.zeros(*shape, dtype=dtype, device=device)

        self._state = {
            "active": zeros(lanes, H, m), "pending": zeros(lanes, H, m),
            "age": zeros(lanes, dtype=torch.long), "wait": zeros(lanes, dtype=torch.long) - 1,
            "until": zeros(lanes, dtype=torch.long), "pause": zeros(lanes, dtype=torch.long),
            "history": zeros(lanes, H, H, m), "count": zeros(lanes, dtype=torch.long),
        }  # fmt: skip

    def _start(self, td: TensorDictBase, init: torch.Tensor) -> torch.Tensor:
        """Reset lanes: their first chunk, ready at once. Returns the mask of such lanes."""
        st = self._state
        if bool(init.any()):
            chunk = self._query(td, init)
            st["active"] = st["active"].to(chunk.dtype)
            st["active"][init] = chunk
            st["age"][init] = 0
            st["wait"][init] = -1
            st["pause"][init] = 0
            st["until"][init] = self.execute - self.delay
        return init.clone()

    def _async_step(self, td, init) -> tuple[torch.Tensor, torch.Tensor]:
        """``naive`` and ``rtc``: arrivals, then queries, then the current chunk's action."""
        st, d = self._state, self.delay
        switch = self._start(td, init)
        arrive = st["wait"] == 0
        if bool(arrive.any()):
            st["active"][arrive] = st["pending"][arrive]
            st["age"][arrive] = d
            st["wait"][arrive] = -1
            switch |= arrive
        ask = st["until"] == 0
        if bool(ask.any()):
            chunk = self._inpaint(td, ask) if self.mode == "rtc" else self._query(td, ask)
            if d == 0:
                st["active"][ask] = chunk
                st["age"][ask] = 0
                switch |= ask
            else:
                st["pending"] = st["pending"].to(chunk.dtype)
                st["pending"][ask] = chunk
                st["wait"][ask] = d
            st["until"][ask] = self.execute
        action = st["active"][torch.arange(st["age"].shape[0], device=st["age"].device), st["age"]]
        st["age"] += 1
        st["until"] -= 1
        st["wait"] = torch.where(st["wait"] > 0, st["wait"] - 1, st["wait"])
        return action, switch

    def _sync_step(self, td, init) -> tuple[torch.Tensor, torch.Tensor]:
        """``sync``: a chunk run out queries and holds still for ``d`` steps."""
        st, d = self._state, self.delay
        self._start(td, init)
        ask = (st["age"] >= self.execute) & (st["pause"] == 0)
        if bool(ask.any()):
            chunk = self._query(td, ask)
            st["pending"] = st["pending"].to(chunk.dtype)
            st["pending"][ask] = chunk
            st["pause"][ask] = d
            st["age"][ask] = 0
        waiting = st["pause"] > 0
        ready = ask & ~waiting  # d = 0: the chunk executes at once
        st["active"][ready] = st["pending"][ready]
        lanes = torch.arange(st["age"].shape[0], device=st["age"].device)
        hold = self.hold.to(st["active"].dtype) if self.hold is not None else None
        action = st["active"][lanes, st["age"]].clone()
        if hold is not None and bool(waiting.any()):
            action[waiting] = hold
        switch = (st["age"] == 0) & ~waiting
        st["pause"] = torch.where(waiting, st["pause"] - 1, st["pause"])
        done = waiting & (st["pause"] == 0)  # the wait ends: the chunk runs from the next step
        st["active"][done] = st["pending"][done]
        st["age"] = torch.where(waiting, st["age"], st["age"] + 1)
        return action, switch

    def _ensemble_step(self, td, init) -> tuple[torch.Tensor, torch.Tensor]:
        """``ensemble``: a query every step, averaged over the chunks that have arrived."""
        st, H, d = self._state, self.horizon, self.delay
        chunk = self._query(td, torch.ones_like(init))
        history = torch.roll(st["history"].to(chunk.dtype), 1, dims=1)
        history[:, 0] = chunk
        st["history"] = history
        st["count"] = torch.where(init, 1, (st["count"] + 1).clamp(max=H))
        j = torch.arange(H, device=chunk.device)
        count = st["count"][:, None]
        first = j[None, :] == count - 1  # the episode's first chunk, ready at once
        valid = (j[None, :] < count) & ((j[None, :] >= d) | first)
        logw = self.ensemble * j.to(chunk.dtype)  # ACT: exp(-m i), i = 0 the oldest
        w = torch.where(
            valid, torch.exp(logw - _stabiliser(logw, valid, self.ensemble * (H - 1))), 0.0
        )
        w = w / w.sum(-1, keepdim=True)
        action = (w[..., None] * history[:, j, j]).sum(1)
        switch = init | (count[:, 0] > d)
        return action, switch


_EXP_SAFE = 80.0
"""``exp(-x)`` for ``x`` up to this is a normal float32 (``exp(-80)`` is 1.8e-35)"""


def _stabiliser(logw: torch.Tensor, valid: torch.Tensor, span: float) -> torch.Tensor:
    """What ensembling's log-weights are taken relative to: the oldest slot's, as the
    committed runs took them, while no arrived weight can underflow against it (``m (H -
    1)`` up to :data:`_EXP_SAFE`; ACT's ``m`` of 0.01 is far below); else each lane's
    largest arrived one (past about 100 every arrived weight underflowed: a review saw NaN
    actions, 0 / 0, and the newest chunk's weight was lost before that)."""
    if span <= _EXP_SAFE:  # span: the log-weights' range, m (H - 1)
        return logw.max()
    return logw.expand_as(valid).masked_fill(~valid, -math.inf).amax(-1, keepdim=True)


def _check(network, H: int, d: int, s: int, latency: Latency, hold, hold_noise: bool) -> None:
    """What a mode needs of the chunk, the delay and the network (module docstring)."""
    mode = latency.mode
    if mode in ("naive", "rtc") and not d <= s <= H - d:
        raise ValueError(
            f"{mode} execution needs delay <= execute <= horizon - delay (the next chunk must "
            f"arrive before this one runs out): delay {d}, execute {s}, horizon {H}"
        )
    if mode == "sync" and not 1 <= s <= H:
        raise ValueError(f"sync execution needs 1 <= execute <= horizon {H}, got {s}")
    if mode == "sync" and hold is None:
        raise ValueError(
            "sync execution holds the robot still while it waits: give hold (hold_action(spec))"
        )
    if mode == "ensemble" and d >= H:
        raise ValueError(f"ensemble execution needs delay < horizon {H}, got delay {d}")
    if mode == "rtc" and not callable(getattr(network, "inpaint", None)):
        raise ValueError(
            f"rtc inpaints the next chunk with a guided sampler (a flow or a diffusion policy, "
            f"inpaint(td, target, weights, guidance)); {type(network).__name__} has none"
        )
    if hold_noise and not callable(getattr(network, "draw_noise", None)):
        raise ValueError(f"hold_noise needs draw_noise(n); {type(network).__name__} has none")

"""Executing action chunks: a learner predicts H actions, a policy acts one step at a time.

:class:`ChunkedPolicy` wraps a network that writes a flat ``ACTION`` ``[*B, H * m]``
(any continuous head of :mod:`imitrl.policies.heads`, a diffusion or flow policy over
the tiled action spec) and acts as a TensorDictModule ``OBSERVATION, is_init -> ACTION``
that rollouts, ``evaluate`` and DAgger's behaviour policy run unchanged:

* **receding horizon** (``ChunkExecution(horizon=H, execute=k)``, Diffusion Policy):
  query the network, execute the first ``k <= H`` actions of the chunk open loop, then
  replan. ``k = 1`` replans every step; ``k = H`` executes the whole chunk.
* **temporal ensembling** (``ChunkExecution(horizon=H, ensemble=m)``, ACT, Zhao et al.
  2023, Sec. 3.3): query every step; the action at step ``t`` is the weighted mean of
  every chunk predicted at ``t' in (t - H, t]`` for step ``t``, with weights
  ``w_i = exp(-m * i)`` where ``i = 0`` is the *oldest* prediction
  (:func:`ensemble_weights`). ACT uses ``m = 0.01``.

* **held noise** (``hold_noise=True``, either mode): a generative network that samples
  from starting noise (:class:`~imitrl.learners.flow.FlowPolicy`, which has
  ``draw_noise``) gets one draw per lane at each reset, passed as ``POLICY_NOISE`` to
  every query of that episode. The network's map from noise to chunk is
  deterministic, so the episode keeps the mode its draw chose instead of drawing it
  again at every replan; across episodes the draws still cover every mode. Measured on
  the two-way task (``flow_chunk``, BC, 6 seeds x 500 episodes): with 8 Euler steps,
  success 0.90 with a fresh draw per replan and 0.93 held; with 32 steps 0.92 fresh and
  0.96 held (0.96 held at 16 steps too; ``benchmarks/README.md``).

* **observation history** (``history=n``, Diffusion Policy's ``T_o``): the network reads
  ``"<key>_history"`` ``[*B, n, *obs]``, the lane's last ``n`` observations (oldest
  first, the first since its reset repeated before it), which the policy keeps from
  the observations it is given: the rows' history
  (:func:`~imitrl.data.history.observation_history`) at act time, in rollouts, DAgger's
  rounds and evaluation alike.

State lives across calls (the current plan, its age, the last ``H`` chunks) per lane
of a batched env, and is dropped where TorchRL's ``InitTracker`` marks a reset
(``is_init``): wrap the env with :func:`chunk_env`. A policy without ``is_init`` in its
input fails loudly rather than run every lane as if it had just been reset.

Why not ``torchrl.modules.MultiStepActorWrapper``: it does the receding horizon
(``replan_interval``) but not temporal ensembling, and it keeps its cache in the
tensordict that the env carries from step to step; this module keeps both modes in
one place with the state in the module (``tests/data/test_chunks.py`` checks the actions
both modes execute against hand-computed ones).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.envs import EnvBase, InitTracker, TransformedEnv

from imitrl import keys
from imitrl.checks import finite_at_least, whole
from imitrl.data.chunks import ACTION_CHUNK, IS_INIT
from imitrl.data.history import history_key

__all__ = [
    "ACT_ENSEMBLE_M",
    "ChunkExecution",
    "ChunkedPolicy",
    "chunk_env",
    "ensemble_weights",
    "reset_lanes",
    "tile_spec",
]


ACT_ENSEMBLE_M = 0.01
"""``m`` of ACT's temporal-ensembling weights ``exp(-m i)`` (the paper's value)"""


@dataclass(frozen=True)
class ChunkExecution:
    """How a chunked policy executes its chunks."""

    horizon: int
    """``H``: actions predicted per query"""
    execute: int | None = None
    """receding horizon: actions executed per query, ``1 <= k <= H`` (None: H)"""
    ensemble: float | None = None
    """temporal ensembling with weights ``exp(-m * i)`` (oldest ``i = 0``); exclusive
    with ``execute``"""
    hold_noise: bool = False
    """draw the network's starting noise once per episode and lane (at its reset) and
    pass it to every query as ``POLICY_NOISE``; the network needs ``draw_noise(n)``"""

    def __post_init__(self) -> None:
        if not whole(self.horizon, 1):
            raise ValueError(f"horizon must be a positive integer, got {self.horizon!r}")
        if self.ensemble is not None and self.execute is not None:
            raise ValueError("give execute (receding horizon) or ensemble (ACT), not both")
        if self.execute is not None and not (
            whole(self.execute, 1) and self.execute <= self.horizon
        ):
            raise ValueError(
                f"execute must be in [1, {self.horizon}], an integer, got {self.execute!r}"
            )
        if self.ensemble is not None and not finite_at_least(self.ensemble, 0):
            raise ValueError(f"ensemble (m) must be finite and >= 0, got {self.ensemble!r}")

    @property
    def replan_every(self) -> int:
        """Steps between queries: ``k``, or 1 when ensembling."""
        return 1 if self.ensemble is not None else (self.execute or self.horizon)


def ensemble_weights(count: int, m: float) -> torch.Tensor:
    """``[count]`` ACT's weights ``w_i = exp(-m * i) / sum_j exp(-m * j)``, oldest first."""
    w = torch.exp(-float(m) * torch.arange(int(count), dtype=torch.float64))
    return w / w.sum()


def tile_spec(spec: Bounded, horizon: int) -> Bounded:
    """The ``[H * m]`` spec of a flat chunk of ``H`` actions of ``spec`` ``[m]``."""
    if not isinstance(spec, Bounded) or len(spec.shape) != 1:
        raise ValueError(f"chunks need a Bounded action spec of shape [m], got {spec!r}")
    low, high = spec.space.low, spec.space.high
    return Bounded(low.repeat(horizon), high.repeat(horizon), shape=(horizon * low.numel(),))


def reset_lanes(tensordict: TensorDictBase) -> torch.Tensor:
    """``[L]`` bool: which lanes of ``tensordict`` (flattened) were just reset (``is_init``);
    a chunked policy keeps state per lane and fails loudly without it."""
    init = tensordict.get(IS_INIT, None)
    if init is None:
        raise ValueError(
            f"a chunked policy needs {IS_INIT!r} to know where a lane was reset: wrap the env "
            "with imitrl.policies.chunking.chunk_env(env) (TorchRL's InitTracker), or set it "
            "True to plan afresh"
        )
    return init.reshape(tensordict.batch_size.numel()).bool()


def chunk_env(env: EnvBase) -> TransformedEnv:
    """``env`` with TorchRL's ``InitTracker``: it writes ``is_init`` (True after a reset)."""
    return TransformedEnv(env, InitTracker())


class ChunkedPolicy(TensorDictModuleBase):
    """``OBSERVATION, is_init -> ACTION_CHUNK, ACTION``: execute a network's chunks.

    Args:
        network: writes a flat ``ACTION`` ``[*B, H * m]`` from the inputs it reads.
        action_dim: ``m``.
        execution: the horizon and how chunks are executed.

    Writes ``ACTION_CHUNK`` ``[*B, H, m]`` (the chunk predicted at this step, or the one
    being executed) and ``ACTION`` ``[*B, m]`` (the executed action).
    """

    def __init__(
        self,
        network: TensorDictModuleBase,
        action_dim: int,
        execution: ChunkExecution,
        *,
        history: int | None = None,
        history_keys: tuple = (keys.OBSERVATION,),
    ) -> None:
        super().__init__()
        if execution.hold_noise and not callable(getattr(network, "draw_noise", None)):
            raise ValueError(
                f"hold_noise needs a network that samples from noise it can draw "
                f"(draw_noise(n), as FlowPolicy has); {type(network).__name__} has none"
            )
        self.network = network
        self.action_dim = int(action_dim)
        self.execution = execution
        self.history = None if history is None else int(history)
        sources = {history_key(k): k for k in history_keys} if history is not None else {}
        for key in sources:
            if key not in network.in_keys:
                raise ValueError(f"the network does not read the history {key!r} it is given")
        self._history_sources = sources  # history key -> the observation it stacks
        self.in_keys = [sources.get(k, k) for k in network.in_keys] + [IS_INIT]
        self.out_keys = [ACTION_CHUNK, keys.ACTION]
        self._plan: torch.Tensor | None = None  # [L, H, m] the chunk being executed
        self._age: torch.Tensor | None = None  # [L] steps since the plan was made
        self._history: torch.Tensor | None = None  # [L, H, H, m], slot j: made j steps ago
        self._count: torch.Tensor | None = None  # [L] chunks in the history since the reset
        self._noise: torch.Tensor | None = None  # [L, d] this episode's draw (hold_noise)
        self._seen: dict = {}  # history key -> [L, n, *obs] the lane's last observations

    def predict(
        self, tensordict: TensorDictBase, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The network's chunk ``[*B, H, m]`` at ``tensordict``'s inputs (no state), from
        the starting ``noise`` ``[*B, d]`` when given (``POLICY_NOISE``)."""
        td = tensordict.select(*self.network.in_keys, strict=True)
        if noise is not None:
            td.set(keys.POLICY_NOISE, noise)
        flat = self.network(td).get(keys.ACTION)
        return flat.unflatten(-1, (self.execution.horizon, self.action_dim))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        lanes = batch.numel()
        init = reset_lanes(tensordict)
        if self._plan is None or self._plan.shape[0] != lanes:
            if not bool(init.all()):
                raise ValueError("a chunked policy's first call must follow a reset of every lane")
            self._reset_state(lanes, init.device)
        if self.execution.hold_noise and bool(init.any()):
            draw = self.network.draw_noise(int(init.sum()))
            if self._noise is None or self._noise.shape != (lanes, draw.shape[-1]):
                self._noise = torch.zeros(
                    lanes, draw.shape[-1], dtype=draw.dtype, device=draw.device
                )
            self._noise[init.to(draw.device)] = draw
        flat_td = tensordict.reshape(lanes) if len(batch) != 1 else tensordict
        if self._history_sources:  # a copy: the caller's tensordict gets no history
            flat_td = self._with_history(flat_td.copy(), init)
        if self.execution.ensemble is not None:
            chunk, action = self._ensemble_step(flat_td, init)
        else:
            chunk, action = self._receding_step(flat_td, init)
        tensordict.set(ACTION_CHUNK, chunk.reshape(*batch, *chunk.shape[1:]))
        tensordict.set(keys.ACTION, action.reshape(*batch, self.action_dim))
        return tensordict

    def _with_history(self, td: TensorDictBase, init: torch.Tensor) -> TensorDictBase:
        """``td`` with each lane's last ``history`` observations, oldest first, the first
        observation since its reset repeated before it (as rows are padded: the history
        of :func:`~imitrl.data.history.observation_history`)."""
        n = self.history
        for key, source in self._history_sources.items():
            obs = td.get(source)  # [L, *obs]
            seen = self._seen.get(key)
            if seen is None or seen.shape[0] != obs.shape[0] or seen.shape[2:] != obs.shape[1:]:
                if not bool(init.all()):
                    raise ValueError("a history's first call must follow a reset of every lane")
                seen = obs.unsqueeze(1).expand(-1, n, *obs.shape[1:]).clone()
            else:
                seen = torch.cat([seen[:, 1:], obs.unsqueeze(1)], dim=1)
                reset = init.to(seen.device)
                if bool(reset.any()):
                    seen[reset] = obs[reset].unsqueeze(1).expand(-1, n, *obs.shape[1:])
            self._seen[key] = seen
            td.set(key, seen)
        return td

    def _reset_state(self, lanes: int, device: torch.device) -> None:
        """Each lane's plan on ``device``: where the lanes' tensordicts are (the env's, or
        the learner's when :class:`~imitrl.system.device.OnDevice` moved them)."""
        H, m = self.execution.horizon, self.action_dim
        self._plan = torch.zeros(lanes, H, m, device=device)
        self._age = torch.zeros(lanes, dtype=torch.int64, device=device)
        self._history = torch.zeros(lanes, H, H, m, device=device)
        self._count = torch.zeros(lanes, dtype=torch.int64, device=device)
        self._noise = None
        self._seen = {}

    def _receding_step(
        self, td: TensorDictBase, init: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        assert self._plan is not None and self._age is not None  # forward set the state
        replan = init | (self._age >= self.execution.replan_every)
        if bool(replan.any()):
            fresh = self.predict(td[replan], None if self._noise is None else self._noise[replan])
            self._plan = self._plan.to(fresh.dtype)
            self._plan[replan] = fresh
            self._age[replan] = 0
        action = self._plan[torch.arange(self._plan.shape[0], device=self._age.device), self._age]
        self._age += 1
        return self._plan.clone(), action

    def _ensemble_step(
        self, td: TensorDictBase, init: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        assert self._history is not None and self._count is not None  # forward set the state
        ensemble = self.execution.ensemble
        assert ensemble is not None  # forward takes this step only with an ensemble
        H = self.execution.horizon
        chunk = self.predict(td, self._noise)  # [L, H, m]
        history = torch.roll(self._history.to(chunk.dtype), 1, dims=1)
        history[:, 0] = chunk
        self._history = history
        self._count = torch.where(init, 1, (self._count + 1).clamp(max=H))
        # the prediction for now made j steps ago is chunk_{t-j}[j]; ACT's i counts
        # from the oldest, i = count - 1 - j: w_j = exp(-m (count - 1 - j)), normalised
        j = torch.arange(H, device=chunk.device)
        preds = history[:, j, j]  # [L, H, m]
        valid = j[None, :] < self._count[:, None]
        logw = -ensemble * (self._count[:, None] - 1 - j[None, :]).to(chunk.dtype)
        w = torch.where(valid, torch.exp(logw), 0.0)
        w = w / w.sum(-1, keepdim=True)
        return chunk, (w[..., None] * preds).sum(1)

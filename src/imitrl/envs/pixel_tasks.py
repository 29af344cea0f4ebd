"""Pixel tasks drawn with torch alone (no rendering stack), each with a privileged state expert.

Both envs write the state under ``"observation"`` (what their expert reads) and an
image under ``"pixels"``: uint8 ``[*batch, H, W, 3]`` (TorchRL's and LeRobot's layout),
drawn at every reset and step, so tests and benchmarks run anywhere. The moving point
is a green Gaussian blob of ``blob`` pixels' standard deviation, so its position is
readable below the pixel size (the intensities interpolate it).

:class:`PixelTwoWayEnv` is :class:`~imitrl.envs.multimodal.TwoWayObstacleEnv` (same
dynamics, rewards, seeding and keys) drawn as an image:

* red: the disc (static);
* blue: the goal segment ``|y| <= goal_halfwidth`` on the goal line (static);
* green: the moving point.

Its view spans ``x in [0, goal_x]`` left to right and ``y in [-half_height,
half_height]`` top (``+y``) to bottom; a point outside the view is not drawn. Its
privileged expert (:func:`state_expert`) reads ``(x, y)`` and nothing else: the task's
expert with its intent fixed to the side the point is on (above for ``y >= 0``). That
action flips at ``y = 0``, which a pixel learner cannot fit near the line.

:class:`PixelBalanceEnv` (hold a ball on an unstable hilltop) has a smooth expert
(:func:`balance_expert`, proportional control) and punishes compounding errors: the
task on which DAgger from pixels clearly beats BC (``benchmarks/camera.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.envs.multimodal import ObstacleGeometry, TwoWayObstacleEnv, _TwoWayExpert
from imitrl.policies.experts import Expert

__all__ = ["Hilltop", "PixelBalanceEnv", "PixelTwoWayEnv", "balance_expert", "state_expert"]

_GEOMETRY = ObstacleGeometry()


class PixelTwoWayEnv(TwoWayObstacleEnv):
    """The two-way obstacle task with a ``"pixels"`` image of it (module docstring).

    Args:
        pixels: ``(H, W)`` of the image.
        half_height: the view spans ``y in [-half_height, half_height]``.
        blob: standard deviation of the point's blob, in pixels.
        batch_size, geometry, seed: as in :class:`TwoWayObstacleEnv`.
    """

    def __init__(
        self,
        *,
        pixels: Sequence[int] = (32, 32),
        half_height: float = 0.6,
        blob: float = 1.0,
        batch_size: Sequence[int] | torch.Size = (),
        geometry: ObstacleGeometry = _GEOMETRY,
        seed: int = 0,
    ) -> None:
        size = tuple(int(p) for p in pixels)
        if len(size) != 2 or min(size) < 4:
            raise ValueError(f"pixels must be (H, W) with both at least 4, got {tuple(pixels)}")
        if not half_height > geometry.radius or not blob > 0:
            raise ValueError(
                f"need half_height > radius ({geometry.radius}) and blob > 0, got "
                f"{half_height}, {blob}"
            )
        super().__init__(batch_size=batch_size, geometry=geometry, seed=seed)
        self.image_size = size
        self.half_height, self.blob = float(half_height), float(blob)
        height, width = size
        # pixel centres in world units: x_c [W] left to right, y_c [H] top (+y) to bottom
        self._x_c = (torch.arange(width) + 0.5) / width * geometry.goal_x
        self._y_c = half_height - (torch.arange(height) + 0.5) / height * 2 * half_height
        self._background = self._draw_background()
        self.observation_spec[keys.PIXELS] = Bounded(
            0, 255, shape=(*self.batch_size, height, width, 3), dtype=torch.uint8
        )

    def _draw_background(self) -> torch.Tensor:
        """``[H, W, 3]`` uint8: the disc (red) and the goal segment (blue)."""
        g = self.geometry
        y, x = torch.meshgrid(self._y_c, self._x_c, indexing="ij")  # [H, W] each
        image = torch.zeros(*self.image_size, 3, dtype=torch.uint8)
        image[..., 0] = torch.where((x - g.obstacle_x) ** 2 + y**2 < g.radius**2, 255, 0)
        last_column = torch.zeros_like(x, dtype=torch.bool)
        last_column[:, -1] = True
        image[..., 2] = torch.where(last_column & (y.abs() <= g.goal_halfwidth), 255, 0)
        return image

    def render_pixels(self) -> torch.Tensor:
        """``[*batch, H, W, 3]`` uint8 image of the current state of every lane."""
        pos = self._pos  # [N, 2]
        scale_x = self.geometry.goal_x / self.image_size[1]  # world units per pixel
        scale_y = 2 * self.half_height / self.image_size[0]
        dx = (self._x_c[None, None, :] - pos[:, 0, None, None]) / scale_x  # [N, 1, W]
        dy = (self._y_c[None, :, None] - pos[:, 1, None, None]) / scale_y  # [N, H, 1]
        blob = torch.exp(-(dx**2 + dy**2) / (2 * self.blob**2))  # [N, H, W]
        image = self._background.expand(pos.shape[0], *self._background.shape).clone()
        image[..., 1] = (blob * 255).round().to(torch.uint8)
        return image.reshape(*self.batch_size, *self.image_size, 3)

    def _td(self, extra: dict) -> TensorDict:
        td = super()._td(extra)
        td.set(keys.PIXELS, self.render_pixels())
        return td


class _StateExpert(nn.Module):
    """``observation [..., 2] -> action [..., 1]``: the task's expert, intent = side of ``y``."""

    def __init__(self, geometry: ObstacleGeometry) -> None:
        super().__init__()
        self.expert = _TwoWayExpert(geometry)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        side = torch.where(obs[..., 1] >= 0, 1, -1).to(torch.int64)
        return self.expert(obs, side)


def state_expert(geometry: ObstacleGeometry = _GEOMETRY) -> Expert:
    """The privileged expert of :class:`PixelTwoWayEnv`: reads ``"observation"`` only.

    It passes the disc on the side the point is on (above when ``y >= 0``) and succeeds
    from every start; it never reads ``"pixels"`` or ``"intent"``.
    """
    return Expert(_StateExpert(geometry), in_keys=[keys.OBSERVATION])


# ------------------------------------------------------------------ the hilltop task
@dataclass(frozen=True)
class Hilltop:
    """Layout and dynamics of :class:`PixelBalanceEnv` (see its docstring)."""

    dt: float = 0.05
    """time step"""
    instability: float = 2.0
    """``lambda`` of ``dp/dt = lambda * p + u``: the hill pushes the ball away from its top"""
    noise: float = 0.02
    """standard deviation of the per-step push ``sigma * xi``, per axis"""
    start: float = 0.35
    """start ``p ~ U(-start, start)^2``: anywhere on the hill the expert can still hold"""
    view: float = 1.0
    """the image spans ``[-view, view]^2``; the episode ends when the ball leaves it"""
    horizon: int = 100
    """the episode is truncated after this many steps (:func:`~imitrl.envs.episode_limit`
    reads it: rollouts of the env need no ``max_steps=``)"""

    def __post_init__(self) -> None:
        for name in ("dt", "instability", "start", "view", "horizon"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.noise < 0:
            raise ValueError(f"noise must be >= 0, got {self.noise}")
        if not self.start < self.point_of_no_return < self.view:
            raise ValueError(
                f"need start ({self.start}) < 1 / instability ({self.point_of_no_return}) "
                f"< view ({self.view}): the expert must be able to hold the ball in view"
            )

    @property
    def point_of_no_return(self) -> float:
        """beyond ``|p_i| > 1 / lambda`` no action in ``[-1, 1]`` brings axis ``i`` back"""
        return 1.0 / self.instability


class PixelBalanceEnv(EnvBase):
    """Hold a ball on a hilltop, seen from above: an unstable 2-D point drawn as an image.

    The state ``p = (x, y)`` follows ``p' = p + dt * (lambda * p + u) + sigma * xi``,
    ``u in [-1, 1]^2``, ``xi ~ N(0, I)`` from the env's generator; the reward is 1 per
    step while the ball is in view (``max |p_i| <= view``), and the episode ends when
    it leaves (terminated) or after ``horizon`` steps (truncated). Past the point of
    no return ``|p_i| > 1 / lambda`` the hill wins: a policy must act before it.

    Why it separates DAgger from BC: the expert (:func:`balance_expert`) brings the ball
    straight to the top and holds it within a pixel or two, so a demonstration shows one
    path and that small patch of the image; a cloned policy's errors, amplified by the
    hill, carry the ball to positions it never saw, where its output is arbitrary, and
    the ball rolls off. DAgger labels exactly those positions.

    Keys: ``"observation"`` float32 ``[*batch, 2]`` (the state, for the privileged
    expert); ``"pixels"`` uint8 ``[*batch, H, W, 3]``: the ball a green Gaussian blob
    of ``blob`` pixels' standard deviation (its sub-pixel position is readable), the
    disc of no return a dim red (static); ``"action"`` float32 ``[*batch, 2]``.

    Args:
        pixels: ``(H, W)`` of the image.
        blob: standard deviation of the ball's blob, in pixels.
        hill: the dynamics and layout.
        batch_size: ``()`` or ``(N,)`` independent lanes.
        seed: seed of the env's ``torch.Generator`` (starts and pushes).
    """

    def __init__(
        self,
        *,
        pixels: Sequence[int] = (32, 32),
        blob: float = 1.5,
        hill: Hilltop = Hilltop(),
        batch_size: Sequence[int] | torch.Size = (),
        seed: int = 0,
    ) -> None:
        size = tuple(int(p) for p in pixels)
        if len(size) != 2 or min(size) < 4:
            raise ValueError(f"pixels must be (H, W) with both at least 4, got {tuple(pixels)}")
        if not blob > 0:
            raise ValueError(f"blob must be positive, got {blob}")
        batch_size = torch.Size(batch_size)
        if len(batch_size) > 1:
            raise ValueError(f"batch_size must be () or (N,), got {tuple(batch_size)}")
        super().__init__(device="cpu", batch_size=batch_size)
        self.hill, self.image_size, self.blob = hill, size, float(blob)
        self._n = int(batch_size.numel())
        height, width = size
        # pixel centres in world units: x_c [W] left to right, y_c [H] top (+y) to bottom
        self._x_c = (2 * (torch.arange(width) + 0.5) / width - 1) * hill.view
        self._y_c = (1 - 2 * (torch.arange(height) + 0.5) / height) * hill.view
        y, x = torch.meshgrid(self._y_c, self._x_c, indexing="ij")  # [H, W]
        inside = x**2 + y**2 <= hill.point_of_no_return**2
        self._background = torch.zeros(height, width, 3, dtype=torch.uint8)
        self._background[..., 0] = torch.where(inside, 64, 0)
        self.observation_spec = Composite(
            {
                keys.OBSERVATION: Unbounded(shape=(*batch_size, 2), dtype=torch.float32),
                keys.PIXELS: Bounded(
                    0, 255, shape=(*batch_size, height, width, 3), dtype=torch.uint8
                ),
            },
            shape=batch_size,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(*batch_size, 2), dtype=torch.float32)
        self.reward_spec = Unbounded(shape=(*batch_size, 1), dtype=torch.float32)
        self.done_spec = Composite(
            {
                key: Categorical(2, shape=(*batch_size, 1), dtype=torch.bool)
                for key in (keys.DONE, keys.TERMINATED, keys.TRUNCATED)
            },
            shape=batch_size,
        )
        self._pos = torch.zeros(self._n, 2)
        self._t = torch.zeros(self._n, dtype=torch.int64)
        self._generator = torch.Generator().manual_seed(int(seed))

    def _set_seed(self, seed: int | None) -> None:
        self._generator = torch.Generator().manual_seed(0 if seed is None else int(seed))

    def render_pixels(self) -> torch.Tensor:
        """``[*batch, H, W, 3]`` uint8 image of the current state of every lane."""
        pos = self._pos  # [N, 2]
        px_x = 2 * self.hill.view / self.image_size[1]  # world units per pixel
        px_y = 2 * self.hill.view / self.image_size[0]
        dx = (self._x_c[None, None, :] - pos[:, 0, None, None]) / px_x  # [N, 1, W]
        dy = (self._y_c[None, :, None] - pos[:, 1, None, None]) / px_y  # [N, H, 1]
        blob = torch.exp(-(dx**2 + dy**2) / (2 * self.blob**2))  # [N, H, W]
        image = self._background.expand(pos.shape[0], *self._background.shape).clone()
        image[..., 1] = (blob * 255).round().to(torch.uint8)
        return image.reshape(*self.batch_size, *self.image_size, 3)

    def _td(self, extra: dict) -> TensorDict:
        obs = {keys.OBSERVATION: self._pos.reshape(*self.batch_size, 2).clone()}
        obs[keys.PIXELS] = self.render_pixels()
        return TensorDict({**obs, **extra}, batch_size=self.batch_size)

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        lanes = torch.ones(self._n, dtype=torch.bool)
        if tensordict is not None and "_reset" in tensordict.keys():
            lanes = tensordict.get("_reset").reshape(self._n)
        # one draw per lane, reset or not, so a lane's stream is fixed
        u = torch.rand(self._n, 2, generator=self._generator, dtype=torch.float64)
        start = ((2 * u - 1) * self.hill.start).float()
        self._pos = torch.where(lanes[:, None], start, self._pos)
        self._t = self._t.masked_fill(lanes, 0)
        false = torch.zeros((*self.batch_size, 1), dtype=torch.bool)
        return self._td(
            {keys.DONE: false, keys.TERMINATED: false.clone(), keys.TRUNCATED: false.clone()}
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION)
        if not action.dtype.is_floating_point or action.numel() != 2 * self._n:
            raise ValueError(
                f"PixelBalanceEnv expects float actions of shape {(*self.batch_size, 2)}, "
                f"got {action.dtype} {tuple(action.shape)}"
            )
        if torch.isnan(action).any():
            raise ValueError("NaN action given to PixelBalanceEnv")
        h = self.hill
        u = action.reshape(self._n, 2).float().clamp(-1.0, 1.0)
        xi = torch.randn(self._n, 2, generator=self._generator)
        self._pos = self._pos + h.dt * (h.instability * self._pos + u) + h.noise * xi
        self._t = self._t + 1
        fell = self._pos.abs().amax(-1) > h.view
        truncated = (self._t >= h.horizon) & ~fell
        shape1 = (*self.batch_size, 1)
        return self._td(
            {
                keys.REWARD: (~fell).float().reshape(shape1),
                keys.DONE: (fell | truncated).reshape(shape1),
                keys.TERMINATED: fell.reshape(shape1),
                keys.TRUNCATED: truncated.reshape(shape1),
            }
        )


class _Proportional(nn.Module):
    """``observation [..., 2] -> clip(-gain * p, -1, 1) [..., 2]``."""

    def __init__(self, gain: float) -> None:
        super().__init__()
        self.gain = float(gain)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.shape[-1:] != (2,):
            raise ValueError(f"observations must be (x, y) [..., 2], got {tuple(obs.shape)}")
        return (-self.gain * obs.float()).clamp(-1.0, 1.0)


def balance_expert(gain: float = 8.0, hill: Hilltop = Hilltop()) -> Expert:
    """The privileged expert of :class:`PixelBalanceEnv`: ``u = clip(-gain * p, -1, 1)``.

    It reads ``"observation"`` only. Its action is Lipschitz in the state (constant
    ``gain``): a pixel learner can fit it everywhere, the boundary included. Unclipped,
    each axis contracts by ``1 + dt * (lambda - gain)`` per step (0.7 by default);
    ``gain`` must exceed ``lambda`` for the ball to stay on the hill.
    """
    if not gain > hill.instability:
        raise ValueError(
            f"gain must exceed the instability ({hill.instability}) to hold the ball, got {gain}"
        )
    return Expert(_Proportional(gain), in_keys=[keys.OBSERVATION])

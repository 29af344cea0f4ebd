"""`PixelTwoWayEnv`: the two-way obstacle task drawn as an image, rendered with torch alone.

The env is :class:`~imitrl.envs.multimodal.TwoWayObstacleEnv` (same dynamics, rewards,
seeding and keys) with one more observation, ``"pixels"``: uint8 ``[*batch, H, W, 3]``
(TorchRL's and LeRobot's layout), drawn at every reset and step without any rendering
stack, so tests and benchmarks run anywhere:

* red: the disc (static);
* blue: the goal segment ``|y| <= goal_halfwidth`` on the goal line (static);
* green: the moving point, a Gaussian blob of ``blob`` pixels' standard deviation, so
  its position is readable below the pixel size (the intensities interpolate it).

The view spans ``x in [0, goal_x]`` left to right and ``y in [-half_height,
half_height]`` top (``+y``) to bottom; a point outside the view is not drawn.

The privileged expert (:func:`state_expert`) reads the state ``"observation"`` = ``(x,
y)`` and nothing else: it is the task's expert with its intent fixed to the side the
point is on (above for ``y >= 0``), a function of the state, so a pixel learner that
sees the point can imitate it. DAgger with it labels the states a pixel learner visits.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import Bounded

from imitrl import keys
from imitrl.envs.multimodal import ObstacleGeometry, TwoWayObstacleEnv, _TwoWayExpert
from imitrl.policies.experts import Expert

__all__ = ["PixelTwoWayEnv", "state_expert"]

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

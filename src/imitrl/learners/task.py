"""What a learner is built for: a task's observation and action spaces (:class:`TaskSpec`).

A :class:`TaskSpec` is read off an env (:meth:`TaskSpec.from_env`) or written by hand
(a benchmark's synthetic task, the study's tabular MDP). The registry's entries read its
plain fields: the number of discrete actions or the ``Bounded`` action spec, and the
observations as integer states or vectors ``[d]``. An env the plain fields cannot
describe (images, multi-discrete, one-hot or unbounded actions) keeps its specs
(``TaskSpec.specs``): the ``for_env`` entry builds from them (a CNN on images).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Categorical, Composite, MultiCategorical, TensorSpec, Unbounded
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.limits import MAX_CATEGORIES

__all__ = ["ACTION_KINDS", "OBSERVED_ENTRIES", "Advantage", "IgnoredObservationWarning", "TaskSpec"]

ACTION_KINDS = ("discrete", "continuous")
"""the action kinds an entry may declare (``for_env`` takes any action spec: ``"any"``)"""

Advantage = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``A(observation, action) -> [N]``, the weights of an advantage-weighted loss"""

OBSERVED_ENTRIES = (keys.OBSERVATION, keys.ENVIRONMENT_STATE, keys.PIXELS)
"""the observation entries an env may give a learner (a Dict env's, as
:class:`~imitrl.envs.DictObservation` names them): one no key of the learner's policy
reads is reported (:meth:`TaskSpec.unread`)"""


class IgnoredObservationWarning(UserWarning):
    """A learner is built for an env whose observation holds an entry its policy never
    reads (:meth:`TaskSpec.unread`): what it cannot see it cannot act on."""


@dataclass(frozen=True)
class TaskSpec:
    """A task's observation and action spaces, as the loss registry reads them."""

    action: int | TensorSpec
    """number of discrete actions, or the ``Bounded`` spec ``[m]`` of a continuous action
    (another action spec only with ``specs``: ``for_env`` builds for it)"""
    observation_dim: int | None = None
    """length of vector observations ``[..., d]`` (the state beside an image too; None
    for integer states, or images alone)"""
    num_states: int | None = None
    """number of integer states ``0 .. S-1`` (None for vector observations or images)"""
    advantage: Advantage | None = field(default=None, compare=False)
    """optional ``A(observation, action) -> [N]`` for advantage-weighted losses"""
    specs: tuple[Composite, TensorSpec] | None = field(default=None, compare=False)
    """the env's unbatched observation and action specs, when read off an env"""

    def __post_init__(self) -> None:
        if self.observation_dim is not None and self.num_states is not None:
            raise ValueError(
                "give exactly one of observation_dim (vectors) or num_states (integers)"
            )
        if self.specs is None and self.observation_dim is None and self.num_states is None:
            raise ValueError(
                "give exactly one of observation_dim (vectors) or num_states (integers)"
            )
        if isinstance(self.action, bool) or not isinstance(self.action, int | TensorSpec):
            raise ValueError(
                f"action must be a number of actions or a Bounded spec, got {self.action!r}"
            )
        if self.specs is None and isinstance(self.action, TensorSpec):
            if not isinstance(self.action, Bounded) or len(self.action.shape) != 1:
                raise ValueError(
                    "a continuous action spec must be Bounded with shape [m], got "
                    f"{type(self.action).__name__} {tuple(self.action.shape)}"
                )

    @property
    def actions(self) -> str:
        """``"discrete"``, ``"continuous"`` (a ``Bounded [m]``), or ``"other"`` (an action
        spec only ``for_env`` builds for)."""
        if isinstance(self.action, int):
            return "discrete"
        if isinstance(self.action, Bounded) and len(self.action.shape) == 1:
            return "continuous"
        return "other"

    @property
    def described(self) -> bool:
        """Whether the plain fields describe the task (integer states or vectors, and
        discrete or ``Bounded`` actions, no image): what every entry but ``for_env``
        needs (an entry that reads images too, ``diffusion_unet``, asks for
        :attr:`observes` and reads :attr:`pixels`)."""
        return self.observes and self.pixels is None

    @property
    def observes(self) -> bool:
        """Whether the plain fields describe the state and the actions (images or not)."""
        observes = self.observation_dim is not None or self.num_states is not None
        return observes and self.actions in ACTION_KINDS

    @property
    def pixels(self) -> tuple[tuple[int, ...], str] | None:
        """``(shape, key)`` of the env's image ``PIXELS`` (``[H, W, C]``), or None."""
        if self.specs is None or keys.PIXELS not in self.specs[0].keys():
            return None
        return tuple(self.specs[0][keys.PIXELS].shape), keys.PIXELS

    def env_specs(self) -> tuple[Composite, TensorSpec]:
        """The observation and action specs: the env's, or built from the plain fields
        (integer states ``Categorical(S)``, vectors ``Unbounded([d])``, actions
        ``Categorical(n)`` or the ``Bounded`` spec)."""
        if self.specs is not None:
            return self.specs
        if self.num_states is not None:
            obs: TensorSpec = Categorical(self.num_states, dtype=torch.int64)
        else:
            assert self.observation_dim is not None  # __post_init__: one of the two is set
            obs = Unbounded((int(self.observation_dim),))
        action = self.action
        if isinstance(action, int):
            action = Categorical(action, dtype=torch.int64)
        return Composite({keys.OBSERVATION: obs}), action

    def unread(self, in_keys: list[NestedKey]) -> dict[str, str]:
        """The entries of :data:`OBSERVED_ENTRIES` in the env's observation spec (when read
        off an env) that none of ``in_keys`` (a policy's) reads, each with its shape
        (``"[39]"``) or, for a Dict of cameras, their names. A policy that reads the
        camera is taken to learn from it: the state entries it leaves are the privileged
        ones a vision policy goes without (Meta-World's ``pixels_agent_pos``), not reported."""
        heads = {k if isinstance(k, str) else k[0] for k in in_keys}
        if self.specs is None or keys.PIXELS in heads:
            return {}
        observed, out = self.specs[0], {}
        for key in OBSERVED_ENTRIES:
            if key in observed.keys() and key not in heads:
                spec = observed[key]
                named = isinstance(spec, Composite)
                out[key] = f"cameras {sorted(spec.keys())}" if named else list(spec.shape)
        return {k: str(v) for k, v in out.items()}

    @classmethod
    def from_rows(cls, rows: TensorDictBase, *, action: int | TensorSpec | None = None) -> TaskSpec:
        """The task of demonstration rows alone (a dataset recorded on a robot, with no env
        to read specs from): the observation entries the rows hold
        (:data:`OBSERVED_ENTRIES`: a float state ``Unbounded [d]``, integer states
        ``Categorical(max + 1)``, a camera or a Dict of cameras ``uint8 [H, W, C]``), and
        ``action`` (a number of actions or a spec, e.g. a Minari dataset's recorded space)
        or else the range of the actions the rows hold, the expert's labels and the
        executed actions (a DAgger dataset's learner acted on some frames): integers
        ``Categorical(max + 1)``, floats ``Bounded(min, max)`` per dimension (the min and
        max LeRobot's ``stats.json`` records). ValueError naming what is missing or of the
        wrong kind."""
        present = set(rows.keys())
        if keys.EXPERT_ACTION not in present or not present & set(OBSERVED_ENTRIES):
            raise ValueError(
                f"rows need {keys.EXPERT_ACTION!r} and one of {list(OBSERVED_ENTRIES)} to "
                f"describe a task; they hold {sorted(map(str, present))}"
            )
        spec = Composite({})
        for key in OBSERVED_ENTRIES:
            if key in present:
                spec[key] = _observed_spec(rows.get(key), key)
        labels = rows.get(keys.EXPERT_ACTION)
        executed = rows.get(keys.ACTION) if keys.ACTION in present else None
        if executed is not None and (
            executed.dtype == labels.dtype and executed.shape == labels.shape
        ):  # a DAgger dataset's learner acted too: the task holds what was executed
            labels = torch.cat([labels, executed])
        if action is None:
            action = _action_range(labels)
        return cls.from_specs(spec, action)

    @classmethod
    def from_env(cls, env: EnvBase) -> TaskSpec:
        """The task of ``env`` (batched or not): :meth:`from_specs` of its unbatched
        observation and action specs."""
        return cls.from_specs(env.observation_spec_unbatched, env.action_spec_unbatched)

    @classmethod
    def from_specs(
        cls,
        observation: int | TensorSpec | None,
        action: int | TensorSpec,
        *,
        pixels: tuple[int, ...] | TensorSpec | None = None,
        pixel_key: NestedKey = keys.PIXELS,
    ) -> TaskSpec:
        """The task of these spaces: ``observation`` a ``Composite`` (an env's observation
        spec), the ``OBSERVATION`` spec alone, a vector width ``d``, or None (images
        alone); ``action`` a number of discrete actions or an action spec; ``pixels``
        ``(H, W, C)`` (or a uint8 spec) of an image under ``pixel_key`` beside it. The plain
        fields are filled where they describe the task (integer states or ``[d]``
        vectors; a ``Categorical`` or ``Bounded [m]`` action)."""
        if isinstance(observation, Composite):
            spec = observation.clone()
        else:
            spec = Composite({})
            if isinstance(observation, int):
                spec[keys.OBSERVATION] = Unbounded((observation,))
            elif observation is not None:
                spec[keys.OBSERVATION] = observation
        if pixels is not None:
            image = pixels if isinstance(pixels, TensorSpec) else None
            if image is None:
                image = Bounded(0, 255, tuple(int(x) for x in pixels), dtype=torch.uint8)
            spec[pixel_key] = image
        if isinstance(action, int):
            action = Categorical(action, dtype=torch.int64)
        obs = spec.get(keys.OBSERVATION, None)
        if obs is not None and obs.dtype.is_floating_point and obs.dtype != torch.float32:
            # a hostile review: a GymWrapper of a float64 env built a learner that failed
            # in its first matmul ("Double and Float"), then blamed another env
            raise ValueError(
                f"the observations are {obs.dtype}; imitrl's learners compute in float32: make "
                "the env with imitrl.envs.make_env (which casts them), or append TorchRL's "
                "DoubleToFloat() transform"
            )
        dim = states = None
        if isinstance(obs, Categorical) and not isinstance(obs, MultiCategorical):
            states = int(obs.space.n)
        elif obs is not None and len(obs.shape) == 1 and not isinstance(obs, Categorical):
            dim = int(obs.shape[0])
        act: int | TensorSpec = action
        if isinstance(action, Categorical) and not isinstance(action, MultiCategorical):
            act = int(action.space.n)
        return cls(
            action=act,
            observation_dim=dim,
            num_states=states,
            specs=(spec, action),
        )


CONSTANT_RANGE = 1e-3
"""how far a constant action dimension's bounds are set apart (relative, at least absolute)"""


def _observed_spec(value: torch.Tensor | TensorDictBase, key: str) -> TensorSpec:
    """The spec of one observation entry ``[N, ...]`` of demonstration rows."""
    if isinstance(value, TensorDictBase):  # a Dict of cameras
        return Composite({k: _observed_spec(value.get(k), k) for k in value.keys()})
    if value.dtype == torch.uint8 and value.dim() == 4:
        return Bounded(0, 255, tuple(value.shape[1:]), dtype=torch.uint8)
    if key != keys.PIXELS and value.dim() == 1 and not value.is_floating_point():
        return Categorical(_categories(value, f"{key!r} (integer states)"), dtype=torch.int64)
    if key != keys.PIXELS and value.dim() == 2 and value.is_floating_point():
        return Unbounded((int(value.shape[1]),), dtype=torch.float32)
    raise ValueError(
        f"rows' {key!r} is {value.dtype} {list(value.shape)}: expected float32 [N, d], "
        "integer states [N] or uint8 images [N, H, W, C]"
    )


def _action_range(labels: torch.Tensor) -> int | TensorSpec:
    """Integer labels ``[N]``: their number; float ones ``[N, m]``: ``Bounded(min, max)``
    (a constant dimension widened by :data:`CONSTANT_RANGE` of its size each way)."""
    if labels.numel() == 0:
        raise ValueError("no expert actions in the rows to take the action range from")
    if not labels.is_floating_point() and labels.dim() == 1:
        return _categories(labels, f"{keys.EXPERT_ACTION!r} (integer actions)")
    if labels.is_floating_point() and labels.dim() == 2:
        low, high = labels.amin(0).float(), labels.amax(0).float()
        # a dimension the expert never varied (a gripper held shut) gets a sliver of range:
        # bounds need low < high, and the squashed output stays at the recorded value
        flat = high - low < CONSTANT_RANGE
        margin = CONSTANT_RANGE * high.abs().clamp(min=1.0)
        low, high = torch.where(flat, low - margin, low), torch.where(flat, high + margin, high)
        return Bounded(low, high, (int(labels.shape[1]),), dtype=torch.float32)
    raise ValueError(
        f"rows' {keys.EXPERT_ACTION!r} is {labels.dtype} {list(labels.shape)}: expected "
        "integer actions [N] or float ones [N, m]"
    )


def _categories(values: torch.Tensor, what: str) -> int:
    """The number of integer values ``values`` ``[N]`` take, ``max + 1``: ValueError
    naming ``what`` for a negative one or more than :data:`~imitrl.limits.MAX_CATEGORIES`."""
    low, high = int(values.min()), int(values.max())
    if low < 0 or high >= MAX_CATEGORIES:
        raise ValueError(
            f"rows' {what} range over [{low}, {high}]: expected integers in [0, "
            f"{MAX_CATEGORIES}) (imitrl.limits.MAX_CATEGORIES; the network is as wide as their "
            "number)"
        )
    return high + 1

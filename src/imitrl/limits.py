"""Every number a command takes, range-checked in one place, with its limits documented.

A numeric field of a command's config (:mod:`imitrl.jobs.configs`,
:class:`~imitrl.jobs.evaluate.EvalJob`,
:class:`~imitrl.experiments.frozenlake.config.StudyConfig`) is declared with
:func:`bounded`, which records its :class:`Bound` in the field's metadata. The one
record serves three readers:

* the config's ``__post_init__`` calls :func:`check_bounds`, so the command line, the
  library's Python API (``BCJob(steps=...)``) and a checkpoint's saved config
  (:mod:`imitrl.jobs.checkpoint`) meet the same checks before any work starts;
* ``--help`` shows the range beside the field's docstring (:mod:`imitrl.cli.flags`);
* a refusal is one line naming the flag, what it must be and what it got
  (``--demos must be an integer in [0, 10_000], got 1000000000000``).

The upper limits bound what an unbounded value would exhaust (memory, or time before
anything useful is done); each is one constant below, its reason in its docstring.
Integers are Python or numpy integers, never bools or floats (``2.5`` episodes is a
mistake, not a count); reals are finite. Limits are written with ``_`` between
thousands, as Python and the command line (``--steps 1_000_000``) both read them.

The hidden layers (``--hidden``, a :func:`widths` field) are checked by
:func:`check_hidden`: each width, their number, and the weights they imply
(:func:`hidden_parameters`), which a checkpoint's weights file must also be large
enough to hold (:mod:`imitrl.jobs.checkpoint`).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "FLOAT32_MAX",
    "MAX_BATCH",
    "MAX_CATEGORIES",
    "MAX_ENV_STEPS",
    "MAX_EPISODES",
    "MAX_EPISODE_STEPS",
    "MAX_EVAL_EPISODES",
    "MAX_FPS",
    "MAX_KERNEL_ENTRIES",
    "MAX_LAYERS",
    "MAX_NPROC",
    "MAX_NUM_ENVS",
    "MAX_PARAMETERS",
    "MAX_ROLLOUT_STEPS",
    "MAX_ROUNDS",
    "MAX_SEED",
    "MAX_STEPS",
    "MAX_THREADS",
    "MAX_UPDATES",
    "MAX_WIDTH",
    "MAX_WORKERS",
    "MIN_ALPHA",
    "Bound",
    "Widths",
    "bounded",
    "check_bounds",
    "check_hidden",
    "flag",
    "flag_of",
    "hidden_parameters",
    "widths",
]

MAX_SEED = 2**31 - 1
"""largest seed: numpy's and gymnasium's seeds are non-negative and below 2**32, and a
job adds small offsets to a seed (evaluation lane ``i`` plays ``eval_seed + i``, study
block ``k`` seeds ``ex_seed + k``), which must stay below it"""
MAX_EPISODES = 10_000
"""most episodes collected for training at once (``--demos``, ``--episodes-per-round``):
their rows are held in memory, up to 10^7 at 1,000 steps an episode"""
MIN_ALPHA = 1e-12
"""smallest error rate of a comparison (``--alpha``): below it ``1 - alpha`` rounds to 1 in
floating point, and no count of episodes could show a difference at it"""
MAX_EVAL_EPISODES = 100_000
"""most evaluation episodes (``--eval-episodes``): only their returns are kept, but
100,000 episodes of 1,000 steps are 10^8 env steps, hours of stepping"""
MAX_NUM_ENVS = 256
"""most env copies stepped together (``--num-envs``): each is an env in memory (a
MuJoCo model, a renderer) and every step waits for all of them"""
MAX_EPISODE_STEPS = 1_000_000
"""longest time limit (``--max-episode-steps``): one episode of an env that never ends
by itself runs to it, and its rows are held until it ends"""
MAX_STEPS = 10_000_000
"""most gradient steps of one fit (``--steps``): the fit records a loss per step, and 10^7
steps of even a small network take hours"""
MAX_BATCH = 1 << 20
"""most rows in one gradient step (``--batch-size``, ``--minibatch-size``,
``--discriminator-batch``): activations for every row at once; the same bound as a
full-batch fit's (:attr:`imitrl.algorithms.bc.BCConfig.full_batch_max_rows`)"""
MAX_ROUNDS = 10_000
"""most DAgger rounds (``--rounds``): each is a fit and a round of episodes, and each
round's record is kept"""
MAX_FPS = 100_000
"""highest recording rate of a LeRobot dataset imitrl writes (``--save-lerobot``): frames
``1/fps`` s apart must stay farther apart than LeRobot's timestamp tolerance, 1e-4 s"""
MAX_WORKERS = 1024
"""most Ray workers (``--workers``): each is a process holding an env and the expert"""
MAX_NPROC = 1024
"""most data-parallel ranks of one command (``--nproc``)"""
MAX_ENV_STEPS = 1_000_000_000
"""most environment steps of an adversarial run (``--total-steps``): 10^9 steps are days
of stepping on any machine this library runs on"""
MAX_ROLLOUT_STEPS = 1 << 20
"""most environment steps held in memory at once (``--rollout-steps``,
``--normalizer-warmup``): a round's batch, with its rewards and advantages"""
MAX_UPDATES = 10_000
"""most optimizer passes per adversarial round (``--ppo-epochs``,
``--discriminator-updates``): the round is repeated that many times"""
MAX_THREADS = 1024
"""most torch threads (``--threads``): more threads than cores slow a fit down
(``benchmarks/README.md``, threads), and torch refuses counts past a C int"""
MAX_WIDTH = 1 << 16
"""widest hidden layer (``--hidden``, and a checkpoint's ``hidden``)"""
MAX_CATEGORIES = 1 << 16
"""most integer states or actions a task read from rows may have
(:meth:`imitrl.learners.TaskSpec.from_rows`, ``imitrl bc --env none``): each is a one-hot
input or an output of the network, as wide as the widest hidden layer
(:data:`MAX_WIDTH`); a dataset's largest label must not size a network by itself"""
MAX_KERNEL_ENTRIES = 1 << 26
"""most entries ``S x A x S`` a tabular model read from an env may have
(:meth:`imitrl.tabular.TabularMDP.from_gym`: its kernel is dense, float64): 2^26 are 512
MiB, a 64x64 FrozenLake map; value iteration's 1000 sweeps over it take about half a
minute on one core, and a map twice as wide would ask 8 GiB and minutes"""
MAX_LAYERS = 64
"""most hidden layers (``--hidden``)"""
MAX_PARAMETERS = 100_000_000
"""most weights the hidden layers may imply (:func:`hidden_parameters`): 10^8 float32
weights are 400 MB, 1.6 GB with their gradients and Adam's two moments, for every
network the learner builds (a policy, and a value network beside it)"""


def _shown(value: Any) -> str:
    """``repr(value)``, short: an integer too long to print (Python refuses past 4,300
    digits) is named by its size."""
    try:
        text = repr(value)
    except ValueError:
        return "an integer of more than 4,300 digits"
    return text if len(text) <= 80 else text[:77] + "..."


def _number(x: float) -> str:
    """A limit as it is typed: ``10_000``, ``0``, ``0.5``."""
    return f"{int(x):_}" if float(x).is_integer() else f"{x:g}"


FLOAT32_MAX = 3.4028234663852886e38
"""the largest finite float32: a real setting past it is inf once it meets a tensor"""
_PAST_FLOAT32 = f" (past float32's largest finite value, {FLOAT32_MAX:.4g})"


@dataclass(frozen=True)
class Bound:
    """The values a numeric field may take: ``low <= x <= high`` (``low < x`` when
    ``low_open``), integers or finite reals, and None when ``none_ok``."""

    low: float
    """smallest value"""
    high: float = math.inf
    """largest value (inf: no upper limit, for a field no value of which exhausts
    anything)"""
    integer: bool = True
    """an integer count (True) or a finite real (False)"""
    low_open: bool = False
    """``low`` itself is refused (a learning rate: ``> 0``)"""
    high_open: bool = False
    """``high`` itself is refused (an error rate: ``< 1``)"""
    none_ok: bool = False
    """None is allowed (``none`` on the command line)"""

    def describe(self, none: str = "none") -> str:
        """What a value must be: ``an integer in [1, 10_000]``, ``> 0 and finite or none``
        (``none``: the word for None, ``null`` in a JSON file)."""
        return self._range() + (f" or {none}" if self.none_ok else "")

    def _range(self) -> str:
        if self.integer:
            if math.isinf(self.high):
                return f"an integer >= {_number(self.low)}"
            return f"an integer in [{_number(self.low)}, {_number(self.high)}]"
        if math.isinf(self.high):
            return f"{'>' if self.low_open else '>='} {_number(self.low)} and finite"
        left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
        return f"in {left}{_number(self.low)}, {_number(self.high)}{right}"

    def _kind(self, none: str) -> str:
        """What a value that is no finite number of the right kind (a string, a nan, a
        float for an integer) must be: the range, said as a kind where it reads better."""
        if not self.integer and math.isinf(self.high) and self.low == 0:
            kind = "a positive number" if self.low_open else "a non-negative number"
            return kind + (f" or {none}" if self.none_ok else "")
        return self.describe(none)

    def help(self, default: Any) -> str:
        """The range as ``--help`` shows it (``default``: the field's, a tuple for a tuple
        field, whose every value is checked)."""
        return ("each " if isinstance(default, tuple) else "") + self.describe()

    def check_field(self, value: Any, name: str, *, none: str = "none") -> None:
        """:meth:`check` ``value``, or each of its values when it is a tuple or a list."""
        if isinstance(value, tuple | list):
            for item in value:
                self.check(item, name, among=value, none=none)
        else:
            self.check(value, name, none=none)

    def holds(self, value: Any) -> bool:
        """Whether ``value`` is one of the values this bound allows."""
        if value is None:
            return self.none_ok
        if not (self._typed(value) and self._above(value)):
            return False
        return value < self.high if self.high_open else value <= self.high

    def check(self, value: Any, name: str, *, among: Any = None, none: str = "none") -> None:
        """Raise ValueError, one line naming ``name``, unless ``value`` is in range.

        ``among``: the whole tuple ``value`` is one element of (shown after it); ``none``:
        the word for None in the message.
        """
        if self.holds(value):
            return
        got = _shown(value) + ("" if among is None else f" in {_shown(list(among))}")
        if not isinstance(value, numbers.Real) or isinstance(value, bool):  # a wrong type
            raise ValueError(
                f"{name} must be {self._kind(none)}, got {got} ({type(value).__name__})"
            )
        if not self._typed(value):  # a float for an integer, a nan, an inf
            past = "" if self.integer or not math.isfinite(value) else _PAST_FLOAT32
            raise ValueError(f"{name} must be {self._kind(none)}, got {got}{past}")
        if self.integer and not self._above(value):  # the side it missed: its smallest
            raise ValueError(f"{name} must be an integer >= {_number(self.low)}, got {got}")
        raise ValueError(f"{name} must be {self.describe(none)}, got {got}")

    def _typed(self, value: Any) -> bool:
        if isinstance(value, bool):
            return False
        if self.integer:
            return isinstance(value, numbers.Integral)
        # finite where it is computed: every real setting meets float32 tensors (an lr of
        # 1e39 passed a float64 check, then overflowed inside Adam)
        return isinstance(value, numbers.Real) and abs(float(value)) <= FLOAT32_MAX

    def _above(self, value: Any) -> bool:
        # ``value``: any real number (an int, a float, a numpy scalar); typeshed's
        # ``numbers.Real`` declares no reflected comparison with a float
        return value > self.low if self.low_open else value >= self.low


def bounded(
    default: Any,
    low: float,
    high: float = math.inf,
    *,
    integer: bool = True,
    low_open: bool = False,
    high_open: bool = False,
    none_ok: bool = False,
    **metadata: Any,
) -> Any:
    """A dataclass field of ``default`` whose values :func:`check_bounds` holds to
    ``Bound(low, high, ...)`` (``metadata``: the field's other switches, e.g.
    ``aliases`` for :mod:`imitrl.cli.flags`)."""
    bound = Bound(
        low, high, integer=integer, low_open=low_open, high_open=high_open, none_ok=none_ok
    )
    return field(default=default, metadata={**metadata, "bound": bound})


class Widths:
    """The values ``--hidden`` takes: :func:`check_hidden`'s (a :func:`widths` field)."""

    def help(self, default: Any) -> str:
        """The limits as ``--help`` shows them."""
        return (
            f"widths in [1, {MAX_WIDTH:_}], at most {MAX_LAYERS} layers implying at most "
            f"{MAX_PARAMETERS:_} weights, or none"
        )

    def check_field(self, value: Any, name: str, *, none: str = "none") -> None:
        """:func:`check_hidden`."""
        check_hidden(value, name, none=none)


def widths(default: tuple[int, ...] | None = None) -> Any:
    """A dataclass field of hidden layer widths, checked by :func:`check_hidden`."""
    return field(default=default, metadata={"bound": Widths()})


def flag(name: str) -> str:
    """The command-line flag of field ``name``: ``eval_episodes`` -> ``--eval-episodes``."""
    return "--" + name.replace("_", "-")


def flag_of(f: dataclasses.Field) -> str:
    """The command-line flag of the dataclass field ``f``: its metadata's ``flag`` where
    it names one (``BCConfig.num_steps`` is ``--steps``), else :func:`flag` of its name."""
    return f.metadata.get("flag") or flag(f.name)


def check_bounds(config: Any, *, name: Callable[[str], str] | None = None) -> None:
    """Check every :func:`bounded` (and :func:`widths`) field of the dataclass instance
    ``config`` (a tuple field: each of its values), in field order; ValueError naming the
    first out of range: by its flag (a command's config), or as ``name`` says (``str``:
    by the field's own name, a library config's)."""
    for f in dataclasses.fields(config):
        bound = f.metadata.get("bound")
        if bound is not None:
            shown = flag_of(f) if name is None else name(f.name)
            bound.check_field(getattr(config, f.name), shown)


def hidden_parameters(hidden: Sequence[int], inputs: int = 1, outputs: int = 1) -> int:
    """The weights an MLP with hidden layers ``hidden`` has at least: ``inputs x h_0 +
    sum_i h_i x h_(i+1) + h_last x outputs`` plus a bias per unit (``inputs`` = 1 and
    ``outputs`` = 1 when the env is not known: a lower bound for any env)."""
    widths = [int(inputs), *map(int, hidden), int(outputs)]
    return sum(a * b + b for a, b in zip(widths, widths[1:]))


def check_hidden(hidden: Any, name: str = "--hidden", *, none: str = "none") -> None:
    """``hidden`` is None or at most :data:`MAX_LAYERS` widths in ``[1, MAX_WIDTH]`` that
    imply at most :data:`MAX_PARAMETERS` weights; ValueError naming ``name`` otherwise
    (``none``: the word for None, ``null`` in a JSON file)."""
    if hidden is None:
        return
    widths = list(hidden) if isinstance(hidden, tuple | list) else None
    if (
        widths is None
        or len(widths) > MAX_LAYERS
        or not all(
            isinstance(h, numbers.Integral) and not isinstance(h, bool) and 1 <= int(h) <= MAX_WIDTH
            for h in widths
        )
    ):
        raise ValueError(
            f"{name} must be a list of layer widths in [1, {MAX_WIDTH}], at most "
            f"{MAX_LAYERS} of them, or {none}; got {_shown(hidden)}"
        )
    implied = hidden_parameters(widths)
    if implied > MAX_PARAMETERS:
        raise ValueError(
            f"{name} {','.join(map(str, widths))} asks for at least {implied:_} weights, "
            f"more than the {MAX_PARAMETERS:_} a network may have "
            "(imitrl.limits.MAX_PARAMETERS)"
        )

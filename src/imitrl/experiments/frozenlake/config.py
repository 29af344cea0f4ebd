"""Configuration of the FrozenLake study (`imitrl frozenlake`).

Every number is range-checked by the :class:`~imitrl.limits.Bound` its field
declares (:func:`~imitrl.limits.bounded`: the range ``--help`` shows, and the one
line a value out of it is refused with), before any work is done. The upper limits are
those of every command (:mod:`imitrl.limits`: seeds, episodes, gradient steps,
rounds, time limits) and the study's own below.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

from gymnasium.envs.toy_text.frozen_lake import MAPS

from imitrl.configs.value_iteration import VALUE_ITERATION_GAMMA, VALUE_ITERATION_SWEEPS
from imitrl.limits import (
    MAX_EPISODE_STEPS,
    MAX_EPISODES,
    MAX_EVAL_EPISODES,
    MAX_ROUNDS,
    MAX_SEED,
    MAX_STEPS,
    Bound,
    bounded,
    check_bounds,
)

__all__ = [
    "MAP_LETTERS",
    "MAX_CHAIN_DRAWS",
    "MAX_DATASETS",
    "MAX_EVAL_SCALE",
    "MAX_SWEEPS",
    "PROTOCOLS",
    "StudyConfig",
    "check_desc",
]

PROTOCOLS = ("faithful", "batched")

MAX_EVAL_SCALE = 1_000
"""largest ``--eval-scale``: the batched protocol plays that many times each evaluation's
episodes (1,000 x the default 1,000 is 10^6 episodes per estimate)"""
MAX_SWEEPS = 100_000
"""most value-iteration sweeps (``--vi-iters``): every sweep's values are kept, ``[sweeps,
S]`` float64 (100,000 sweeps of the 8x8 map: 51 MB)"""
MAX_DATASETS = 1_000
"""most redrawn datasets per setting (``--sweep-datasets``, ``--ex-datasets``, ...): the
batched protocol builds the product MDP of that many copies, and each is fitted"""
MAX_CHAIN_DRAWS = 10_000_000
"""most coin flips of one compounding-error panel, ``--chain-samples`` x its horizon T:
they are drawn at once, ``[samples, T]`` (10^7: about 300 MB with the sums over them)"""
MAP_LETTERS = {"S": "start", "F": "frozen", "H": "hole", "G": "goal"}
"""The letters of a FrozenLake map (``--desc``)."""
_EPS = Bound(0, 1, integer=False, low_open=True)
"""a chain panel's per-step error eps"""


def check_desc(desc: tuple[str, ...]) -> None:
    """Raise ``ValueError`` unless ``desc`` is a FrozenLake map the study can score.

    Rows of one length, only the letters of :data:`MAP_LETTERS`, exactly one start
    ``S`` and at least one goal ``G`` (without one, gymnasium's model gives the holes
    the best entering reward among terminal states, and they would count as goals).
    """
    rows = list(desc)
    shown = ",".join(rows)
    if not rows or not all(rows):
        raise ValueError(f"--desc needs non-empty rows, e.g. SFFF,FHFH,FFFH,HFFG; got {shown!r}")
    if len({len(r) for r in rows}) != 1:
        raise ValueError(
            f"--desc rows must all have the same length, got lengths "
            f"{[len(r) for r in rows]} in {shown}"
        )
    if len(rows[0]) < 2:  # gymnasium's FrozenLake reads the map as a 2-d grid of columns
        raise ValueError(
            f"--desc needs at least 2 columns (gymnasium's FrozenLake cannot build a map of "
            f"one column); got {shown!r}: write the corridor as one row, e.g. "
            f"{''.join(rows)!r}"
        )
    bad = sorted(set("".join(rows)) - set(MAP_LETTERS))
    if bad:
        letters = ", ".join(f"{k} ({v})" for k, v in MAP_LETTERS.items())
        raise ValueError(f"--desc letters must be {letters}; got {bad} in {shown}")
    starts = shown.count("S")
    if starts != 1:
        raise ValueError(f"--desc needs exactly one start S, got {starts} in {shown}")
    if "G" not in shown:
        raise ValueError(f"--desc has no goal G in {shown}: success is reaching a G cell")


@dataclass(frozen=True)
class StudyConfig:
    """Every knob of the study; the defaults reproduce the section's numbers."""

    out: Path = Path("results/frozenlake")
    """output directory (report.txt, results.json, figures)"""
    protocol: str = "faithful"
    """faithful: gymnasium's own random stream, seeded per block (the section's digits);
    batched: independent TabularEnv lanes, replicates vectorised, eval_scale x more episodes"""
    eval_scale: int = bounded(100, 1, MAX_EVAL_SCALE)
    """batched protocol: evaluation episodes multiplier"""
    env_id: str = "FrozenLake-v1"
    """gymnasium toy-text env id"""
    map_name: str | None = None
    """gymnasium map name ("4x4", "8x8"); None = the env default"""
    desc: tuple[str, ...] | None = None
    """custom map rows, e.g. SFFF,FHFH,FFFH,HFFG (overrides map_name)"""
    slippery: bool | None = None
    """is_slippery passed to gym.make; None = the env's own default (FrozenLake: slippery)"""
    max_steps: int | None = bounded(
        None, 1, MAX_EPISODE_STEPS, none_ok=True, aliases=("--max-episode-steps",)
    )
    """episode time limit (--max-episode-steps, as in every other command, or
    --max-steps); None = the env's registered limit (100 for FrozenLake 4x4); needed for
    envs registered without one, such as CliffWalking-v1"""
    gamma: float = bounded(VALUE_ITERATION_GAMMA, 0, 1, integer=False, low_open=True)
    """discount of the expert's value iteration"""
    vi_iters: int = bounded(VALUE_ITERATION_SWEEPS, 1, MAX_SWEEPS)
    """value-iteration sweeps"""
    lr: float = bounded(0.1, 0, integer=False, low_open=True)
    """Adam learning rate of the tabular clone"""
    probe_states: tuple[int, ...] = bounded((9, 3), 0)
    """states whose pi(.|s) is printed after the fit"""
    demo_episodes: int = bounded(3, 1, MAX_EPISODES)
    """expert episodes of the main demonstration set"""
    demo_seed: int = bounded(0, 0, MAX_SEED)
    """seed of the demonstration block"""
    fit_steps: int = bounded(200, 1, MAX_STEPS)
    """full-batch Adam steps of the main fit and of every DAgger round"""
    eval_episodes: int = bounded(1000, 1, MAX_EVAL_EPISODES)
    """episodes per success-rate estimate"""
    eval_seed: int = bounded(1, 0, MAX_SEED)
    """seed of the expert-vs-clone evaluation block"""
    sweep_sizes: tuple[int, ...] = bounded((1, 3, 10), 1, MAX_EPISODES)
    """dataset sizes (episodes) of the sweep"""
    sweep_datasets: int = bounded(10, 1, MAX_DATASETS)
    """datasets per size"""
    sweep_fit_steps: int = bounded(50, 1, MAX_STEPS)
    """Adam steps per sweep fit"""
    sweep_eval_episodes: int = bounded(300, 1, MAX_EVAL_EPISODES)
    """episodes per sweep evaluation"""
    sweep_seed: int = bounded(2, 0, MAX_SEED)
    """seed of the sweep block"""
    chain_seed: int = bounded(3, 0, MAX_SEED)
    """numpy seed of the compounding-error chain (each panel draws from a fresh generator)"""
    chain_samples: int = bounded(20000, 1, MAX_CHAIN_DRAWS)
    """simulated imitators per chain panel"""
    chain_panels: tuple[tuple[float, int], ...] = ((0.05, 10), (0.01, 64))
    """(per-step error eps, longest horizon T) of each panel: eps in (0, 1], T an integer
    in [1, 1_000_000] (a time limit's range), and --chain-samples x T at most 10_000_000
    coin flips (MAX_CHAIN_DRAWS: a panel draws them at once)"""
    tv_steps: tuple[int, ...] = bounded((3, 5, 10, 20), 1, MAX_EPISODE_STEPS)
    """steps at which the total variation between the state distributions is printed"""
    dagger_rounds: int = bounded(4, 1, MAX_ROUNDS)
    """DAgger fits (a relabel round is collected after each)"""
    dagger_episodes: int = bounded(3, 1, MAX_EPISODES)
    """relabelled episodes per round"""
    dagger_seed: int = bounded(4, 0, MAX_SEED)
    """seed of the DAgger block"""
    exercises: bool = True
    """run the four exercises"""
    ex_demo_counts: tuple[int, ...] = bounded((5, 20, 100, 500), 1, MAX_EPISODES)
    """exercise 2: number of demonstration episodes N"""
    ex_datasets: int = bounded(10, 1, MAX_DATASETS)
    """exercises 2-5: datasets (seeds) per setting"""
    ex_fit_steps: int = bounded(50, 1, MAX_STEPS)
    """exercises: Adam steps per fit"""
    ex_error_datasets: int = bounded(50, 1, MAX_DATASETS)
    """exercise 3: three-episode datasets pooled for per-state errors"""
    ex_corruption: float = bounded(0.1, 0, 1, integer=False)
    """exercise 5: fraction of corrupted expert labels"""
    ex_seed: int = bounded(5, 0, MAX_SEED)
    """seed of the exercise blocks (one block per exercise: ex_seed, ex_seed + 1, ...)"""
    irl: bool = True
    """run section 8, maximum-entropy IRL (``--no-irl`` skips it)"""
    irl_steps: int = bounded(100, 1, MAX_STEPS)
    """Adam steps of each IRL fit (exact likelihood gradient)"""
    irl_lr: float = bounded(0.5, 0, integer=False, low_open=True)
    """Adam learning rate of the IRL fits"""
    irl_sizes: tuple[int, ...] = bounded((1, 3, 10), 1, MAX_EPISODES)
    """section 8: demonstration episodes per redrawn dataset"""
    irl_datasets: int = bounded(10, 1, MAX_DATASETS)
    """section 8: redrawn datasets per size (IRL, BC and DAgger from each)"""
    irl_seed: int = bounded(9, 0, MAX_SEED)
    """seed of the section 8 block"""
    irl_transfer: tuple[tuple[str, str], ...] | None = None
    """reward-transfer targets as env constructor arguments ``name:value``
    (``is_slippery:False,success_rate:0.5``); none: those of is_slippery:False,
    success_rate:0.5, success_rate:0.9 that the env takes"""
    airl: bool = True
    """with section 8, run 8b: AIRL's reward against MaxEnt IRL's under changed dynamics
    (``--no-airl`` skips it)"""
    airl_beta: float = bounded(20.0, 0, integer=False, low_open=True)
    """8b: the demonstrator's inverse temperature (soft-optimal for beta x the env's
    reward); AIRL identifies the reward of a Boltzmann-rational demonstrator. From its
    exact occupancy AIRL recovers g to within 1e-10 of the truth plus a constant on the
    4x4 lake at beta 20 (7e-8 at 100); on the 8x8 map at 100 the rarely taken actions are
    too rare to pin it in 200 rounds (error 11). At 20 the demonstrator succeeds with
    probability 0.26 (the greedy expert 0.73) and 1000 of its episodes transfer to every target"""
    airl_sizes: tuple[int, ...] = bounded((10, 100, 1000), 1, MAX_EPISODES)
    """8b: demonstrated episodes per dataset (besides the unlimited-data limit)"""
    airl_rounds: int = bounded(200, 1, MAX_ROUNDS)
    """8b: generator/discriminator rounds of each AIRL fit"""
    airl_seed: int = bounded(10, 0, MAX_SEED)
    """8b: seed of the demonstrator's episodes"""
    progress: bool = True
    """progress bars for the longer blocks"""

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {PROTOCOLS}, got {self.protocol!r}")
        check_bounds(self)  # every number, and each of a tuple's
        scale = next(f.default for f in fields(self) if f.name == "eval_scale")
        if self.protocol == "faithful" and self.eval_scale != scale:
            raise ValueError(
                f"--eval-scale {self.eval_scale} applies to --protocol batched only: the "
                "faithful protocol plays the section's own episode counts"
            )
        for name in ("sweep_sizes", "tv_steps", "ex_demo_counts", "irl_sizes", "airl_sizes"):
            values = getattr(self, name)  # results are keyed by them
            if len(set(values)) != len(values):
                raise ValueError(f"--{name.replace('_', '-')}: each value once, got {list(values)}")
        if not self.tv_steps:
            raise ValueError("--tv-steps: give at least one step (e.g. 3,5,10,20)")
        # the probe states' upper bound needs the env: run_study checks it
        self._check_chain_panels()
        if self.map_name is not None and self.map_name not in MAPS:
            raise ValueError(
                f"--map-name {self.map_name!r} is not a gymnasium FrozenLake map: "
                f"one of {', '.join(MAPS)}, or give the rows with --desc"
            )
        if self.desc is not None:
            check_desc(self.desc)

    def _check_chain_panels(self) -> None:
        """Each ``eps:T`` panel: eps in (0, 1], T a horizon, and ``--chain-samples x T``
        coin flips at most :data:`MAX_CHAIN_DRAWS`."""
        for eps, T in self.chain_panels:
            if not _EPS.holds(eps):
                raise ValueError(
                    f"--chain-panels must be eps:T with eps in (0, 1], got {eps!r} in "
                    f"{list(self.chain_panels)}"
                )
            Bound(1, MAX_EPISODE_STEPS).check(T, "--chain-panels", among=self.chain_panels)
            if self.chain_samples * T > MAX_CHAIN_DRAWS:
                raise ValueError(
                    f"--chain-samples {self.chain_samples} x --chain-panels horizon {T} = "
                    f"{self.chain_samples * T:_} coin flips, more than the {MAX_CHAIN_DRAWS:_} "
                    "one panel draws at once (imitrl.experiments.frozenlake.config."
                    "MAX_CHAIN_DRAWS)"
                )

    @property
    def make_kwargs(self) -> dict:
        kwargs: dict = {} if self.slippery is None else {"is_slippery": self.slippery}
        if self.desc is not None:
            kwargs["desc"] = list(self.desc)
        elif self.map_name is not None:
            kwargs["map_name"] = self.map_name
        return kwargs

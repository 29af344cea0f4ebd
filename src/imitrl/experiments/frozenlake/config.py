"""Configuration of the FrozenLake study (`imitrl frozenlake`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from gymnasium.envs.toy_text.frozen_lake import MAPS

__all__ = ["MAP_LETTERS", "PROTOCOLS", "StudyConfig", "check_desc"]

PROTOCOLS = ("faithful", "batched")


# integer fields that count something (episodes, datasets, steps, sweeps): each >= 1
_COUNTS = (
    "eval_scale",
    "vi_iters",
    "demo_episodes",
    "fit_steps",
    "eval_episodes",
    "sweep_datasets",
    "sweep_fit_steps",
    "sweep_eval_episodes",
    "chain_samples",
    "dagger_rounds",
    "dagger_episodes",
    "ex_datasets",
    "ex_fit_steps",
    "ex_error_datasets",
    "irl_steps",
    "irl_datasets",
    "airl_rounds",
)
_SEEDS = (
    "demo_seed",
    "eval_seed",
    "sweep_seed",
    "chain_seed",
    "dagger_seed",
    "ex_seed",
    "irl_seed",
    "airl_seed",
)
# tuples of counts, each >= 1 and given once (results are keyed by them)
_COUNT_TUPLES = ("sweep_sizes", "tv_steps", "ex_demo_counts", "irl_sizes", "airl_sizes")
MAP_LETTERS = {"S": "start", "F": "frozen", "H": "hole", "G": "goal"}
"""The letters of a FrozenLake map (``--desc``)."""


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _check_count(name: str, value: object, *, least: int = 1, shown: object = None) -> None:
    """Raise unless ``value`` is an integer >= ``least``; ``shown`` is the whole flag value."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
        got = value if shown is None else f"{value!r} in {list(shown)}"
        raise ValueError(f"{_flag(name)} must be an integer >= {least}, got {got}")


def _check_real(name: str, value: object, expected: str, ok: Callable[[float], bool]) -> None:
    """Raise unless ``value`` is a finite real number for which ``ok`` holds."""
    real = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if not (real and math.isfinite(value) and ok(value)):
        raise ValueError(f"{_flag(name)} must be {expected}, got {value!r}")


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
    eval_scale: int = 100
    """batched protocol: evaluation episodes multiplier"""
    env_id: str = "FrozenLake-v1"
    """gymnasium toy-text env id"""
    map_name: str | None = None
    """gymnasium map name ("4x4", "8x8"); None = the env default"""
    desc: tuple[str, ...] | None = None
    """custom map rows, e.g. SFFF,FHFH,FFFH,HFFG (overrides map_name)"""
    slippery: bool | None = None
    """is_slippery passed to gym.make; None = the env's own default (FrozenLake: slippery)"""
    max_steps: int | None = field(default=None, metadata={"aliases": ("--max-episode-steps",)})
    """episode time limit (--max-episode-steps, as in every other command, or
    --max-steps); None = the env's registered limit (100 for FrozenLake 4x4); needed for
    envs registered without one, such as CliffWalking-v1"""
    gamma: float = 0.95
    """discount of the expert's value iteration"""
    vi_iters: int = 1000
    """value-iteration sweeps"""
    lr: float = 0.1
    """Adam learning rate of the tabular clone"""
    probe_states: tuple[int, ...] = (9, 3)
    """states whose pi(.|s) is printed after the fit"""
    demo_episodes: int = 3
    """expert episodes of the main demonstration set"""
    demo_seed: int = 0
    """seed of the demonstration block"""
    fit_steps: int = 200
    """full-batch Adam steps of the main fit and of every DAgger round"""
    eval_episodes: int = 1000
    """episodes per success-rate estimate"""
    eval_seed: int = 1
    """seed of the expert-vs-clone evaluation block"""
    sweep_sizes: tuple[int, ...] = (1, 3, 10)
    """dataset sizes (episodes) of the sweep"""
    sweep_datasets: int = 10
    """datasets per size"""
    sweep_fit_steps: int = 50
    """Adam steps per sweep fit"""
    sweep_eval_episodes: int = 300
    """episodes per sweep evaluation"""
    sweep_seed: int = 2
    """seed of the sweep block"""
    chain_seed: int = 3
    """numpy seed of the compounding-error chain (each panel draws from a fresh generator)"""
    chain_samples: int = 20000
    """simulated imitators per chain panel"""
    chain_panels: tuple[tuple[float, int], ...] = ((0.05, 10), (0.01, 64))
    """(per-step error eps, longest horizon T) of each panel"""
    tv_steps: tuple[int, ...] = (3, 5, 10, 20)
    """steps at which the total variation between the state distributions is printed"""
    dagger_rounds: int = 4
    """DAgger fits (a relabel round is collected after each)"""
    dagger_episodes: int = 3
    """relabelled episodes per round"""
    dagger_seed: int = 4
    """seed of the DAgger block"""
    exercises: bool = True
    """run the four exercises"""
    ex_demo_counts: tuple[int, ...] = (5, 20, 100, 500)
    """exercise 2: number of demonstration episodes N"""
    ex_datasets: int = 10
    """exercises 2-5: datasets (seeds) per setting"""
    ex_fit_steps: int = 50
    """exercises: Adam steps per fit"""
    ex_error_datasets: int = 50
    """exercise 3: three-episode datasets pooled for per-state errors"""
    ex_corruption: float = 0.1
    """exercise 5: fraction of corrupted expert labels"""
    ex_seed: int = 5
    """seed of the exercise blocks (one block per exercise: ex_seed, ex_seed + 1, ...)"""
    irl: bool = True
    """run section 8, maximum-entropy IRL (``--no-irl`` skips it)"""
    irl_steps: int = 100
    """Adam steps of each IRL fit (exact likelihood gradient)"""
    irl_lr: float = 0.5
    """Adam learning rate of the IRL fits"""
    irl_sizes: tuple[int, ...] = (1, 3, 10)
    """section 8: demonstration episodes per redrawn dataset"""
    irl_datasets: int = 10
    """section 8: redrawn datasets per size (IRL, BC and DAgger from each)"""
    irl_seed: int = 9
    """seed of the section 8 block"""
    irl_transfer: tuple[tuple[str, str], ...] | None = None
    """reward-transfer targets as env constructor arguments ``name:value``
    (``is_slippery:False,success_rate:0.5``); none: those of is_slippery:False,
    success_rate:0.5, success_rate:0.9 that the env takes"""
    airl: bool = True
    """with section 8, run 8b: AIRL's reward against MaxEnt IRL's under changed dynamics
    (``--no-airl`` skips it)"""
    airl_beta: float = 20.0
    """8b: the demonstrator's inverse temperature (soft-optimal for beta x the env's
    reward); AIRL identifies the reward of a Boltzmann-rational demonstrator. From its
    exact occupancy AIRL recovers g to within 1e-10 of the truth plus a constant on the
    4x4 lake at beta 20 (7e-8 at 100); on the 8x8 map at 100 the rarely taken actions are
    too rare to pin it in 200 rounds (error 11). At 20 the demonstrator succeeds with
    probability 0.26 (the greedy expert 0.73) and 1000 of its episodes transfer to every target"""
    airl_sizes: tuple[int, ...] = (10, 100, 1000)
    """8b: demonstrated episodes per dataset (besides the unlimited-data limit)"""
    airl_rounds: int = 200
    """8b: generator/discriminator rounds of each AIRL fit"""
    airl_seed: int = 10
    """8b: seed of the demonstrator's episodes"""
    progress: bool = True
    """progress bars for the longer blocks"""

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {PROTOCOLS}, got {self.protocol!r}")
        for name in _COUNTS:
            _check_count(name, getattr(self, name))
        for name in _SEEDS:
            _check_count(name, getattr(self, name), least=0)
        for name in _COUNT_TUPLES:
            values = getattr(self, name)
            for v in values:
                _check_count(name, v, shown=values)
            if len(set(values)) != len(values):
                raise ValueError(f"{_flag(name)}: each value once, got {list(values)}")
        if not self.tv_steps:
            raise ValueError("--tv-steps: give at least one step (e.g. 3,5,10,20)")
        for s in self.probe_states:  # the upper bound needs the env: run_study checks it
            _check_count("probe_states", s, least=0, shown=self.probe_states)
        if self.max_steps is not None:
            _check_count("max_steps", self.max_steps)
        _check_real("gamma", self.gamma, "in (0, 1]", lambda g: 0.0 < g <= 1.0)
        _check_real("lr", self.lr, "> 0", lambda x: x > 0.0)
        _check_real("irl_lr", self.irl_lr, "> 0", lambda x: x > 0.0)
        _check_real("airl_beta", self.airl_beta, "> 0", lambda x: x > 0.0)
        _check_real("ex_corruption", self.ex_corruption, "in [0, 1]", lambda x: 0.0 <= x <= 1.0)
        for eps, T in self.chain_panels:
            _check_real("chain_panels", eps, "eps:T with eps in (0, 1]", lambda e: 0 < e <= 1)
            _check_count("chain_panels", T, shown=self.chain_panels)
        if self.map_name is not None and self.map_name not in MAPS:
            raise ValueError(
                f"--map-name {self.map_name!r} is not a gymnasium FrozenLake map: "
                f"one of {', '.join(MAPS)}, or give the rows with --desc"
            )
        if self.desc is not None:
            check_desc(self.desc)

    @property
    def make_kwargs(self) -> dict:
        kwargs: dict = {} if self.slippery is None else {"is_slippery": self.slippery}
        if self.desc is not None:
            kwargs["desc"] = list(self.desc)
        elif self.map_name is not None:
            kwargs["map_name"] = self.map_name
        return kwargs

"""Configuration of the FrozenLake study (`imitrl frozenlake`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = ["PROTOCOLS", "StudyConfig"]

PROTOCOLS = ("faithful", "batched")


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
    max_steps: int | None = None
    """episode time limit; None = the env's registered limit (100 for FrozenLake 4x4);
    needed for envs registered without one, such as CliffWalking-v1"""
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
    progress: bool = True
    """progress bars for the longer blocks"""

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {PROTOCOLS}, got {self.protocol!r}")
        for name in (
            "eval_scale",
            "vi_iters",
            "demo_episodes",
            "eval_episodes",
            "sweep_datasets",
            "dagger_rounds",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1 or None, got {self.max_steps}")
        if not 0.0 <= self.ex_corruption <= 1.0:
            raise ValueError(f"ex_corruption must be in [0, 1], got {self.ex_corruption}")

    @property
    def make_kwargs(self) -> dict:
        kwargs: dict = {} if self.slippery is None else {"is_slippery": self.slippery}
        if self.desc is not None:
            kwargs["desc"] = list(self.desc)
        elif self.map_name is not None:
            kwargs["map_name"] = self.map_name
        return kwargs

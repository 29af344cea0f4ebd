"""Checkpoints of a DAgger run: everything the next round depends on, saved after each.

One directory (a :meth:`~imitrl.data.DemonstrationBuffer.save` checkpoint: atomic,
verified by checksums) holds after round ``k``:

* the buffer's rows (demonstrations and relabel rounds ``1 .. k + 1``);
* the round's learner with its optimizers (the next round warm-starts from it, and a
  finished run returns it);
* ``state.json``: the next round, the config it was run with, the round records, the
  mixture's coin generator, the episode source's random state (the env's generators,
  the learner's sampling generator or a gymnasium stream's position) and torch's
  global generator.

A run killed at any point resumes from the last complete round and then draws exactly
the numbers the uninterrupted run drew: the buffer, the learner's weights and every
later evaluation are identical to the bit (``tests/test_dagger_resume.py`` kills a
subprocess with SIGKILL after each round).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch

from imitrl.algorithms.bc import BCResult
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.policies.learner import Learner

__all__ = ["FORMAT", "RunState", "generator_state", "load_run", "save_run", "set_generator_state"]

FORMAT = "imitrl.dagger/1"


def generator_state(generator: torch.Generator | None) -> list[int] | None:
    """A torch generator's state as JSON-able integers (None stays None)."""
    return None if generator is None else generator.get_state().tolist()


def set_generator_state(generator: torch.Generator | None, state: list[int] | None) -> None:
    """Restore :func:`generator_state` (ValueError when one side is missing)."""
    if (generator is None) != (state is None):
        raise ValueError("the saved run and this one disagree on having a sampling generator")
    if generator is not None:
        generator.set_state(torch.tensor(state, dtype=torch.uint8))


def config_summary(config) -> dict[str, Any]:
    """What a resumed run must share with the saved one (``rounds`` may grow)."""
    beta = config.beta
    return {
        "episodes_per_round": config.episodes_per_round,
        "warm_start": config.warm_start,
        "seed": config.seed,
        "bc": dataclasses.asdict(config.bc),
        # a dataclass schedule by value; any other callable by its type only
        "beta": repr(beta) if dataclasses.is_dataclass(beta) else type(beta).__qualname__,
    }


def _record_json(record) -> dict[str, Any]:
    out = {f.name: getattr(record, f.name) for f in dataclasses.fields(record) if f.name != "bc"}
    out["bc"] = {
        "losses": record.bc.losses.tolist(),
        "final_loss": record.bc.final_loss,
        "num_rows": record.bc.num_rows,
    }
    return out


def _record_from_json(cls, data: dict[str, Any]):
    bc = data.pop("bc")
    result = BCResult(
        losses=torch.tensor(bc["losses"], dtype=torch.float32),
        final_loss=bc["final_loss"],
        num_rows=bc["num_rows"],
    )
    return cls(**data, bc=result)


@dataclasses.dataclass
class RunState:
    """Where a resumed run starts."""

    next_round: int
    records: list
    bc_step: int
    learner: Learner


def save_run(
    path: Path, buffer: DemonstrationBuffer, learner: Learner, *, next_round: int, config,
    records: list, bc_step: int, mixer_generator: torch.Generator, source,
) -> None:  # fmt: skip
    """Write the checkpoint of a run whose next round is ``next_round`` (atomic)."""
    state = {
        "format": FORMAT,
        "next_round": next_round,
        "config": config_summary(config),
        "records": [_record_json(r) for r in records],
        "bc_step": bc_step,
        "mixer": generator_state(mixer_generator),
        "source": source.state_dict(),
        "torch": torch.get_rng_state().tolist(),
    }
    buffer.save(path, learner=learner, state=state, overwrite=True)  # this run's own, locked


def load_run(
    path: Path, buffer: DemonstrationBuffer, make_learner, *, config, record_cls,
    mixer_generator: torch.Generator, source,
) -> RunState:  # fmt: skip
    """Restore a run saved by :func:`save_run` into ``buffer``, the generators and ``source``.

    ``buffer`` must hold exactly the saved run's first rows (its demonstrations); the
    saved relabel rounds are appended to it. Raises ValueError naming what differs.
    """
    learner = make_learner()
    saved, state = DemonstrationBuffer.load(path, learner=learner)
    if state.get("format") != FORMAT:
        raise ValueError(
            f"{path} is not a DAgger checkpoint (state format {state.get('format')!r})"
        )
    mine = config_summary(config)
    if state["config"] != mine:
        diff = sorted(k for k in mine if mine[k] != state["config"].get(k))
        raise ValueError(f"{path} was saved by a run with another config (differs in {diff})")
    if state["next_round"] > config.rounds:
        raise ValueError(
            f"{path} has {state['next_round']} rounds done; the config asks {config.rounds}"
        )
    n = len(buffer)
    if n > len(saved) or not bool((saved.data[:n] == buffer.data).all()):
        raise ValueError(
            f"the buffer does not hold the demonstrations the run in {path} started from"
        )
    if len(saved) > n:
        buffer.extend(saved.data[n:])
    set_generator_state(mixer_generator, state["mixer"])
    source.load_state_dict(state["source"])
    torch.set_rng_state(torch.tensor(state["torch"], dtype=torch.uint8))
    records = [_record_from_json(record_cls, r) for r in state["records"]]
    return RunState(state["next_round"], records, state["bc_step"], learner)

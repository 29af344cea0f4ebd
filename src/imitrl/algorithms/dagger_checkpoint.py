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
later evaluation are identical to the bit (``tests/algorithms/test_dagger_checkpoint.py`` kills a
subprocess with SIGKILL after each round).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import torch

from imitrl.algorithms.bc import BCResult
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.data.provenance import NO_BETA
from imitrl.learners.learner import Learner
from imitrl.system.ranks import rank_and_world

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
    """What a resumed run must share with the saved one (``rounds`` may grow). The fits'
    batch is the global one (each rank's times the ranks: :mod:`imitrl.system.ranks`),
    so a run saved at N ranks resumes at any M whose ranks hold that batch between them."""
    beta = config.beta
    bc = dataclasses.asdict(config.bc)
    if bc["batch_size"] is not None:
        bc["batch_size"] *= rank_and_world()[1]
    summary = {
        "episodes_per_round": config.episodes_per_round,
        "warm_start": config.warm_start,
        "seed": config.seed,
        "bc": bc,
        # a dataclass schedule by value; any other callable by its type only
        "beta": repr(beta) if dataclasses.is_dataclass(beta) else type(beta).__qualname__,
    }
    if config.gate is not None:  # a gated run's (absent from the runs saved before gates)
        summary.update(gate=repr(config.gate), label=config.label)
    if getattr(config, "shared", None):  # the caller's (absent from runs saved before it)
        summary["shared"] = config.shared
    return summary


def _refuse_batch(path: Path, saved: dict, mine: dict) -> None:
    """ValueError naming the batch when only the global batch differs: the saved run's
    global batch, and what this world size needs (or that it cannot split it)."""
    theirs, ours = saved.get("bc", {}), mine["bc"]
    if not isinstance(theirs, dict) or theirs.get("batch_size") == ours["batch_size"]:
        return
    if {**saved, "bc": {**theirs, "batch_size": None}} != {
        **mine,
        "bc": {**ours, "batch_size": None},
    }:
        return  # something besides the batch differs: the general message names it
    total, world = theirs.get("batch_size"), rank_and_world()[1]
    if not isinstance(total, int) or total <= 0:
        return
    if total % world:
        need = f"{world} ranks cannot split it evenly: resume at a world size dividing it"
    else:
        need = f"at {world} rank(s) give --batch-size {total // world}"
    raise ValueError(
        f"{path} was saved with a global batch of {total} rows (--batch-size times --nproc); {need}"
    )


def _record_json(record) -> dict[str, Any]:
    out = {f.name: getattr(record, f.name) for f in dataclasses.fields(record) if f.name != "bc"}
    out["bc"] = {
        "losses": record.bc.losses.tolist(),
        "final_loss": record.bc.final_loss,
        "num_rows": record.bc.num_rows,
    }
    return out


def _record_from_json(cls, data: Any, path: Path, k: int):
    """Round record ``k`` as saved, rebuilt (ValueError naming the checkpoint otherwise)."""
    try:
        data = dict(data)
        bc = data.pop("bc")
        result = BCResult(
            losses=torch.tensor(bc["losses"], dtype=torch.float32),
            final_loss=bc["final_loss"],
            num_rows=bc["num_rows"],
        )
        return cls(**data, bc=result)
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise ValueError(
            f"{path}: round record {k} is malformed ({type(err).__name__}: {err})"
        ) from None


def _check_records(path: Path, records: list, next_round: int, bc_step: int, demos: int,
                   rows: int) -> None:  # fmt: skip
    """ValueError unless the saved round records are the run the state says: one per
    round done, in order, each of plain values in range, whose fit steps sum to
    ``bc_step`` and whose rows add up from the ``demos`` to the ``rows`` saved (a hostile
    review: 50 copies of the records resumed into 151 rounds, none into one, and a
    ``next_round`` of 0 re-ran round 0 on the relabelled rows)."""
    if len(records) != next_round:
        raise ValueError(f"{path}: {len(records)} round records for {next_round} rounds done")
    if records and records[0].rows_trained != demos:  # a buffer the run extended, given again
        raise ValueError(
            f"the buffer holds {demos} rows; the run in {path} started from "
            f"{records[0].rows_trained} rows of demonstrations: give it those alone"
        )
    trained = demos
    for k, r in enumerate(records):
        where = f"{path}: round record {k}"
        counts = (r.round, r.rows_trained, r.expert_queries, r.rows_collected, r.bc.num_rows)
        if any(type(c) is not int or c < 0 for c in counts) or r.round != k:
            raise ValueError(f"{where}: round, rows and queries must be counts, round {k}")
        if r.rows_trained != trained:
            raise ValueError(f"{where} trained on {r.rows_trained} rows; its rounds make {trained}")
        trained += r.rows_collected
        fractions = [r.beta_next, r.expert_executed_fraction]
        if not all(f is None or (_number(f) and (0 <= f <= 1 or f == NO_BETA)) for f in fractions):
            raise ValueError(f"{where}: beta_next and expert_executed_fraction must be in [0, 1]")
        if not (r.interventions is None or (type(r.interventions) is int and r.interventions >= 0)):
            raise ValueError(f"{where}: interventions must be a count")
        if not (r.info is None or isinstance(r.info, dict)):
            raise ValueError(f"{where}: info must be a JSON object")
        finite = bool(torch.isfinite(r.bc.losses).all()) and _number(r.bc.final_loss)
        if not finite or not math.isfinite(r.bc.final_loss):
            raise ValueError(f"{where}: its fit's losses must be finite numbers")
    steps = sum(int(r.bc.losses.numel()) for r in records)
    if bc_step != steps or trained != rows:
        raise ValueError(
            f"{path}: bc_step {bc_step} and {rows} rows saved; the round records make "
            f"{steps} fit steps and {trained} rows"
        )


def _number(value: Any) -> bool:
    return type(value) in (int, float)


def _uint8_state(value: Any, what: str, path: Path) -> torch.Tensor:
    """A generator's saved state (a list of bytes) as the tensor ``set_state`` takes."""
    if not isinstance(value, list) or not all(type(b) is int and 0 <= b <= 255 for b in value):
        raise ValueError(f"{path}: the {what} generator's state must be a list of bytes")
    return torch.tensor(value, dtype=torch.uint8)


_STATE_TYPES = {"next_round": int, "bc_step": int, "config": dict, "records": list, "source": dict}
"""the entries of a DAgger checkpoint's state and their JSON types"""


def _restore_generators(path, saved_source, mixer, torch_state, mixer_generator, source) -> None:
    """Set the episode source's, the mixture's and torch's generators to the saved states;
    all or none (what each accepts is its own to say: a refusal is a ValueError naming
    the checkpoint, the generators as they were)."""
    before = (source.state_dict(), generator_state(mixer_generator), torch.get_rng_state())
    try:
        source.load_state_dict(saved_source)
        set_generator_state(mixer_generator, None if mixer is None else mixer.tolist())
        torch.set_rng_state(torch_state)
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as err:
        source.load_state_dict(before[0])
        set_generator_state(mixer_generator, before[1])
        torch.set_rng_state(before[2])
        raise ValueError(
            f"{path}: the saved generators do not fit this run ({type(err).__name__}: {err})"
        ) from None


@dataclasses.dataclass
class RunState:
    """Where a resumed run starts."""

    next_round: int
    records: list
    bc_step: int
    learner: Learner | None
    """the saved learner; None before the first round's fit"""


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


def _check_state(path: Path, state: Any, config) -> None:
    """ValueError unless ``state`` is a DAgger checkpoint's, saved with ``config``'s
    settings (:func:`config_summary`; a run saved before ``shared`` compares without)."""
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        found = state.get("format") if isinstance(state, dict) else state
        raise ValueError(f"{path} is not a DAgger checkpoint (state format {found!r})")
    for name, kind in _STATE_TYPES.items():
        if type(state.get(name)) is not kind:
            raise ValueError(
                f"{path}: state entry {name!r} must be a {kind.__name__}, got "
                f"{type(state.get(name)).__name__}"
            )
    mine = config_summary(config)
    theirs = state["config"].get("shared")
    if "shared" not in state["config"]:
        mine.pop("shared", None)
    elif isinstance(theirs, dict) and isinstance(mine.get("shared"), dict):
        # a key the caller shares now that the saved run did not: compared from then on
        mine["shared"] = {k: v for k, v in mine["shared"].items() if k in theirs}
    if state["config"] != mine:
        _refuse_batch(path, state["config"], mine)
        diff = sorted(k for k in {*mine, *state["config"]} if mine.get(k) != state["config"].get(k))
        if diff == ["shared"]:  # name the caller's settings that differ
            theirs, ours = state["config"]["shared"], mine.get("shared", {})
            if isinstance(theirs, dict):
                diff = sorted(k for k in {*ours, *theirs} if ours.get(k) != theirs.get(k))
        raise ValueError(f"{path} was saved by a run with another config (differs in {diff})")


def load_run(
    path: Path, buffer: DemonstrationBuffer, make_learner, *, config, record_cls,
    mixer_generator: torch.Generator, source,
) -> RunState:  # fmt: skip
    """Restore a run saved by :func:`save_run` into ``buffer``, the generators and ``source``.

    ``buffer`` must hold exactly the saved run's first rows (its demonstrations); the
    saved relabel rounds are appended to it. The checkpoint is read once, by descriptor
    (:meth:`DemonstrationBuffer.load`: its rows held to the bytes present), and every entry
    of its state is checked before anything is changed. Raises ValueError naming what
    differs or what is malformed.
    """
    learner = make_learner()
    try:
        saved, state = DemonstrationBuffer.load(path, learner=learner)
    except (ValueError, RuntimeError):  # a learner of another shape: the configs first
        _check_state(path, DemonstrationBuffer.load(path)[1], config)
        raise
    _check_state(path, state, config)
    if not 0 <= state["next_round"] <= config.rounds:
        raise ValueError(
            f"{path} has {state['next_round']} rounds done; the config asks {config.rounds}"
        )
    if state["bc_step"] < 0:
        raise ValueError(f"{path}: bc_step must be >= 0, got {state['bc_step']}")
    records = [_record_from_json(record_cls, r, path, k) for k, r in enumerate(state["records"])]
    mixer = None if state.get("mixer") is None else _uint8_state(state["mixer"], "mixer", path)
    torch_state = _uint8_state(state.get("torch"), "torch", path)
    n = len(buffer)
    if n > len(saved) or not bool((saved.data[:n] == buffer.data).all()):
        raise ValueError(
            f"the buffer does not hold the demonstrations the run in {path} started from"
        )
    _check_records(path, records, state["next_round"], state["bc_step"], n, len(saved))
    _restore_generators(path, state["source"], mixer, torch_state, mixer_generator, source)
    if len(saved) > n:
        buffer.extend(saved.data[n:])
    return RunState(state["next_round"], records, state["bc_step"], learner)

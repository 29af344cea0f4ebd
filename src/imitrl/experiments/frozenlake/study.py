"""The FrozenLake study: every experiment of the section, then its exercises.

``run_study(config)`` is a function of its config: same config, same digits. It
prints the report, writes ``report.txt``, ``results.json`` and the figures to
``config.out``, and returns the results dict. Every Monte Carlo rate is printed next
to the exact finite-horizon value of the same policy. Every flag is checked before
any work (:mod:`.config`, then against the env's MDP); the outputs go to a staging
folder that replaces ``config.out`` only when the run completes (:mod:`.outputs`).

One module per part, run in this order on one shared :class:`StudyContext`:

* :mod:`.demonstrations` (1. the expert and its demonstrations),
  :mod:`.cloning` (2. behaviour cloning, 3. acting on its own), :mod:`.sweep`
  (4. redrawn datasets), :mod:`.compounding_error` (5. the chain),
  :mod:`.divergence` (6. state distributions), :mod:`.dagger_rounds` (7. DAgger),
  :mod:`.irl` (8. maximum-entropy IRL, exactly; ``--no-irl`` skips it);
  :mod:`.airl_transfer` (8b. AIRL's reward under changed dynamics; ``--no-airl``);
* the exercises :mod:`.ex_demo_counts`, :mod:`.ex_state_errors`, :mod:`.ex_budget`,
  :mod:`.ex_corruption`, built on :mod:`.replicates` (K datasets fitted as one);
* :mod:`.prose_check`, the section's claims against the exact numbers.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from imitrl.experiments.frozenlake import outputs
from imitrl.experiments.frozenlake.airl_transfer import airl_transfer
from imitrl.experiments.frozenlake.backends import BatchedBackend, FaithfulBackend
from imitrl.experiments.frozenlake.cloning import behaviour_cloning, evaluation
from imitrl.experiments.frozenlake.compounding_error import compounding_error
from imitrl.experiments.frozenlake.config import StudyConfig
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.experiments.frozenlake.dagger_rounds import dagger_rounds
from imitrl.experiments.frozenlake.demonstrations import expert_and_demos
from imitrl.experiments.frozenlake.divergence import divergence
from imitrl.experiments.frozenlake.ex_budget import ex_budget
from imitrl.experiments.frozenlake.ex_corruption import ex_corruption
from imitrl.experiments.frozenlake.ex_demo_counts import ex_demo_counts
from imitrl.experiments.frozenlake.ex_state_errors import ex_state_errors
from imitrl.experiments.frozenlake.irl import irl, transfer_mdps
from imitrl.experiments.frozenlake.prose_check import prose_checks
from imitrl.experiments.frozenlake.report import Report
from imitrl.experiments.frozenlake.sweep import sweep
from imitrl.tabular.dp import greedy, value_iteration
from imitrl.tabular.mdp import TabularMDP

__all__ = ["run_study"]


def _check_runnable(config: StudyConfig, mdp: TabularMDP) -> None:
    """Fail loudly on what the study cannot run: no time limit, bad probes, batched + many starts."""
    if mdp.max_steps is None:
        raise ValueError(
            f"{mdp.name!r} is registered without a time limit: give one with --max-steps "
            "(StudyConfig.max_steps); every success rate here is within a horizon"
        )
    late = [t for t in config.tv_steps if t > mdp.max_steps]
    if late:
        raise ValueError(
            f"--tv-steps {late} past the time limit of {mdp.max_steps} steps: no episode "
            "reaches them (give smaller steps, or a larger --max-steps)"
        )
    bad = [s for s in config.probe_states if not 0 <= s < mdp.num_states]
    if bad:
        default = config.probe_states == StudyConfig.probe_states
        raise ValueError(
            f"--probe-states {bad} outside the {mdp.num_states} states of {mdp.name!r}"
            + (" (the default: the section's states of the 4x4 map)" if default else "")
            + "; pass states of this map, e.g. --probe-states 0"
        )
    starts = int((mdp.initial > 0).sum())
    if config.protocol == "batched" and starts != 1:
        raise ValueError(
            f"--protocol batched pins each lane to one start state, and {mdp.name!r} has "
            f"{starts}: run it with --protocol faithful"
        )


def _mdp(config: StudyConfig) -> TabularMDP:
    """The env's MDP, checked against the config (before any output or work)."""
    mdp = TabularMDP.from_gym(
        config.env_id, config.gamma, make_kwargs=config.make_kwargs, max_steps=config.max_steps
    )
    _check_runnable(config, mdp)
    if config.irl:
        transfer_mdps(config)  # --irl-transfer targets the env cannot build: refused now
    return mdp


def _context(config: StudyConfig, mdp: TabularMDP, staging: Path, echo: bool) -> StudyContext:
    """The expert by value iteration, the backend, the report (written to ``staging``)."""
    rep = Report(staging, echo=echo)
    V = value_iteration(mdp, config.vi_iters)[-1]
    expert_table = greedy(mdp.backup(V))
    backend = (
        FaithfulBackend(mdp, expert_table)
        if config.protocol == "faithful"
        else BatchedBackend(mdp, expert_table, config.eval_scale)
    )
    rep.set(
        "config", {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(config).items()}
    )
    rep.set("protocol", config.protocol)
    return StudyContext(config, mdp, expert_table, backend, rep)


def _header(ctx: StudyContext) -> None:
    mdp, config, rep = ctx.mdp, ctx.config, ctx.report
    stochastic = bool((mdp.P.amax(-1) < 1).any())
    rep.line(
        f"imitrl frozenlake: {mdp.name}, {'stochastic' if stochastic else 'deterministic'} "
        f"transitions, time limit {mdp.max_steps}, protocol {config.protocol}"
    )
    if config.protocol == "batched":
        rep.line(
            f"(batched: independent TabularEnv lanes, {config.eval_scale}x the evaluation episodes; numbers differ from the section's)"
        )


def _sections(config: StudyConfig) -> list[tuple[str, Callable[[StudyContext], None]]]:
    """(timing name, section) in the order they run."""
    sections: list[tuple[str, Callable[[StudyContext], None]]] = [
        ("expert", expert_and_demos),
        ("bc", behaviour_cloning),
        ("evaluation", evaluation),
        ("sweep", sweep),
        ("chain", compounding_error),
        ("divergence", divergence),
        ("dagger", dagger_rounds),
    ]
    if config.irl:
        sections.append(("irl", irl))
        if config.airl:
            sections.append(("airl", airl_transfer))
    if config.exercises:
        sections += [
            ("ex_demo_counts", ex_demo_counts),
            ("ex_state_errors", ex_state_errors),
            ("ex_budget", ex_budget),
            ("ex_corruption", ex_corruption),
        ]
    sections.append(("prose", prose_checks))
    return sections


def _write_outputs(rep: Report, timing: dict[str, float], out: Path) -> None:
    """Write report.txt and results.json to the staging folder; the lines name their place in ``out``."""
    rep.set("timing", timing)
    rep.section("Outputs")
    rep.line(f"report: {out / 'report.txt'}")
    rep.line(f"results: {out / 'results.json'}")
    rep.line(f"figures: {', '.join(sorted(p.name for p in rep.out.glob('*.png')))}")
    rep.line(f"wall time: {timing['total']:.1f} s")
    rep.write()


def run_study(config: StudyConfig, *, echo: bool = True) -> dict:
    """Run the whole study (see the module docstring); returns the results dict.

    Every flag is checked before any work. The outputs are written to a staging
    folder beside ``config.out`` and moved there only when the run completes
    (:mod:`.outputs`): an interrupted run leaves the previous results whole.

    Raises:
        ValueError: a config the env cannot run, or an ``out`` that cannot take the results.
    """
    t0 = time.perf_counter()
    mdp = _mdp(config)
    with outputs.staged(config.out) as staging:  # Ctrl-C included: nothing half-written lands
        ctx = _context(config, mdp, staging, echo)
        _header(ctx)
        timing: dict[str, float] = {}
        for name, fn in _sections(config):
            ts = time.perf_counter()
            fn(ctx)
            timing[name] = time.perf_counter() - ts
        timing["total"] = time.perf_counter() - t0
        _write_outputs(ctx.report, timing, config.out)
    return ctx.report.results

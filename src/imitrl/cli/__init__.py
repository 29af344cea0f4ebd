"""Command line: ``imitrl {bc,dagger,gail,airl,eval,bench,frozenlake} [--<field> VALUE ...]``.

Every command is a function of one frozen config dataclass, and every field of that
dataclass is a flag (dashes for underscores) whose help text is the field's
docstring (:mod:`imitrl.cli.flags`). Tuples are comma-separated (``--hidden 64,64``,
``--sweep-sizes 1,3,10``; chain panels as ``eps:T`` pairs, ``--chain-panels
0.05:10,0.01:64``), booleans take ``--flag`` / ``--no-flag``, optional values take
``none``.

=========== ======================= =========================================
command     config                  function
=========== ======================= =========================================
bc          ``jobs.bc.BCJob``        ``jobs.bc.run_bc``
dagger      ``jobs.dagger.DAggerJob`` ``jobs.dagger.run_dagger``
gail        ``jobs.gail.GAILJob``    ``jobs.gail.run_gail``
airl        ``jobs.gail.AIRLJob``    ``jobs.gail.run_airl``
eval        ``jobs.evaluate.EvalJob`` ``jobs.evaluate.run_eval``
bench       ``jobs.bench.BenchJob``  ``jobs.bench.run_bench``
frozenlake  ``StudyConfig``          ``experiments.frozenlake.run_study``
=========== ======================= =========================================

Results and report lines go to stdout, progress bars to stderr; bad input is one
line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import sys
import textwrap
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from imitrl.cli.flags import add_config_flags, config_from_args
from imitrl.experiments.frozenlake import StudyConfig, run_study
from imitrl.jobs import bc, bench, dagger, evaluate, gail
from imitrl.jobs.resolve import EXPERTS
from imitrl.objectives import registry

__all__ = ["COMMANDS", "Command", "build_parser", "main"]


@dataclass(frozen=True)
class Command:
    """One subcommand: its config dataclass, the function it runs, what it prints."""

    config: type
    """frozen dataclass; every field is a flag"""
    run: Callable[[Any], Any]
    """``run(config) -> results``"""
    report: Callable[[Any], list[str]] | None
    """results -> lines for stdout (None: the function prints its own report)"""
    help: str
    """one line in ``imitrl --help``"""
    description: str
    """the top of ``imitrl COMMAND --help``"""


def _names_epilog() -> str:
    """The built-in experts and the registered losses, for ``bc`` / ``dagger`` --help."""
    losses = "\n".join(f"  {e.name:<22} {e.actions:<10} {e.summary}" for e in registry.entries())
    return (
        f"built-in experts (--expert): {', '.join(EXPERTS)}\n\n"
        f"losses (--loss): default, or one of\n{losses}"
    )


COMMANDS: dict[str, Command] = {
    "bc": Command(
        bc.BCJob,
        bc.run_bc,
        bc.report,
        "behaviour cloning on expert demonstrations or a dataset",
        "Fit a learner to expert demonstrations (--demos episodes of --expert) or to a "
        "LeRobot/Minari --dataset, evaluate it beside the expert, and write results.json, "
        "a checkpoint (config.json + learner.pt), curves.png and logs/ to --out.",
    ),
    "dagger": Command(
        dagger.DAggerJob,
        dagger.run_dagger,
        dagger.report,
        "DAgger: BC, then roll the learner, relabel with the expert, aggregate, refit",
        "Round 0 is behaviour cloning on the demonstrations; each later round refits on "
        "the buffer grown by --episodes-per-round learner episodes labelled by --expert. "
        "Every round is evaluated; results.json, the last learner's checkpoint, curves.png "
        "and logs/ go to --out.",
    ),
    "gail": Command(
        gail.GAILJob,
        gail.run_gail,
        gail.report,
        "GAIL: PPO on a discriminator's reward -log(1 - D(s, a)), from demonstrations",
        "Adversarial imitation (Ho & Ermon 2016) from --demos episodes of --expert or a "
        "LeRobot/Minari --dataset: --total-steps env steps of PPO on the discriminator's "
        "reward; no expert queries after the demonstrations. Writes results.json, a "
        "checkpoint (config.json + learner.pt), curves.png and logs/ to --out.",
    ),
    "airl": Command(
        gail.AIRLJob,
        gail.run_airl,
        gail.report,
        "AIRL: PPO on f(s, a, s') - log pi(a|s), f = g(s) + gamma h(s') - h(s)",
        "Adversarial inverse RL (Fu et al. 2018), state-only reward g, from the same "
        "demonstrations and flags as imitrl gail; outputs as imitrl gail.",
    ),
    "eval": Command(
        evaluate.EvalJob,
        evaluate.run_eval,
        evaluate.report,
        "evaluate a saved learner (--checkpoint) or an expert (--expert)",
        "Mean return and its 95% interval over --eval-episodes episodes on the env seeded "
        "--eval-seed (the defaults reproduce the numbers of imitrl bc/dagger).",
    ),
    "bench": Command(
        bench.BenchJob,
        bench.run_bench,
        None,
        "run a benchmark script: imitrl bench NAME [args...]",
        "Run benchmarks/NAME.py of the source checkout with the remaining arguments.",
    ),
    "frozenlake": Command(
        StudyConfig,
        run_study,
        None,
        "reproduce the FrozenLake study (expert, BC, compounding error, DAgger, exercises)",
        "Every experiment of the FrozenLake section on imitrl's pipeline, with the exact value "
        "beside every Monte Carlo estimate. Writes report.txt, results.json and figures to --out.",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    """The ``imitrl`` argument parser: one subcommand per entry of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="imitrl", description="imitrl: imitation learning on TorchRL"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    epilogs = {
        "bc": _names_epilog(),
        "dagger": _names_epilog(),
        "gail": _names_epilog(),
        "airl": _names_epilog(),
        "bench": f"benchmarks: {', '.join(bench.available()) or '(none found)'}",
    }
    for name, command in COMMANDS.items():
        if name in epilogs:  # the lists of names keep their lines
            child = sub.add_parser(
                name,
                help=command.help,
                description=textwrap.fill(command.description, 79),
                epilog=epilogs[name],
                formatter_class=argparse.RawDescriptionHelpFormatter,
            )
        else:
            child = sub.add_parser(name, help=command.help, description=command.description)
        add_config_flags(child, command.config)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``imitrl`` command; returns the exit status (2 on bad input)."""
    args = build_parser().parse_args(argv)
    command = COMMANDS[args.command]
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # torchrl's INFO lines go to stdout
    if args.command == "frozenlake":
        torch.set_num_threads(1)  # the simulators are bandwidth-bound; threads only contend
    try:
        results = command.run(config_from_args(command.config, args))
    except (ValueError, ImportError) as err:  # bad flags, unknown names, missing extras
        print(f"imitrl {args.command}: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # outputs are written whole or not at all (see each job)
        print(f"imitrl {args.command}: interrupted", file=sys.stderr)
        return 130
    if command.report is not None:
        for line in command.report(results):
            print(line)
    if args.command == "bench":
        return int(results["returncode"])
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

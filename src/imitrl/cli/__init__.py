"""Command line: ``imitrl {bc,dagger,gail,airl,eval,compare,bench,frozenlake} [--<field> VALUE ...]``.

Every command is a function of one frozen config dataclass, and every field of that
dataclass is a flag (dashes for underscores) whose help text is the field's
docstring (:mod:`imitrl.cli.flags`). Tuples are comma-separated (``--hidden 64,64``,
``--sweep-sizes 1,3,10``; chain panels as ``eps:T`` pairs, ``--chain-panels
0.05:10,0.01:64``), booleans take ``--flag`` / ``--no-flag``, optional values take
``none``.

=========== ======================= =========================================
command     config                  function
=========== ======================= =========================================
bc          ``jobs.configs.BCJob``   ``jobs.bc.run_bc``
dagger      ``jobs.configs.DAggerJob`` ``jobs.dagger.run_dagger``
gail        ``jobs.configs.GAILJob`` ``jobs.gail.run_gail``
airl        ``jobs.configs.AIRLJob`` ``jobs.gail.run_airl``
eval        ``jobs.evaluate.EvalJob`` ``jobs.evaluate.run_eval``
bench       ``jobs.bench.BenchJob``  ``jobs.bench.run_bench``
frozenlake  ``StudyConfig``          ``experiments.frozenlake.run_study``
=========== ======================= =========================================

Every command also takes ``--threads N``: torch's CPU threads while it runs (default
:data:`~imitrl.system.threads.DEFAULT_THREADS` = 1, measured in
``benchmarks/threads.py``; at most :data:`~imitrl.limits.MAX_THREADS`), set with
:func:`~imitrl.system.threads.set_threads` before the command's function starts;
``bench`` hands it to the script's process as ``OMP_NUM_THREADS`` (torch's starting
thread count there; a benchmark that sets its own keeps its own).

Run as the process's command (the ``imitrl`` script, ``python -m imitrl``), every
command but ``bench`` (which starts a script in a process of its own) imports its
modules with the garbage collector paused and freezes the import-time heap out of its
walks before it runs (:mod:`imitrl.system.heap`: the imports no longer run full
collections over a growing heap, about a second, and the process's exit no longer frees
300,000 to 430,000 objects one by one, about another, on this project's machines).

Results and report lines go to stdout, progress bars to stderr; bad input is one
line on stderr and exit status 2 (a value its flag's type cannot read, as argparse's
error: :class:`~imitrl.cli.flags.OneLineParser`; a number out of its range, or any
other value the config refuses, as the config's ``ValueError``, before any work is
done and before anything is written); a full disk or a folder that cannot be written is one
line on stderr and exit status 1 (the outputs as they were).

Import cost: ``imitrl --help`` imports no command; ``imitrl COMMAND ...`` imports that
command's module alone (:class:`Command`), so ``imitrl --help``, ``imitrl bench`` and
every command's ``--help`` start without torch (``tests/jobs/test_names_imports.py``): the configs
live in :mod:`imitrl.jobs.configs`, the lists of losses and experts in
:mod:`imitrl.jobs.names`.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import signal
import sys
import textwrap
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from imitrl.cli.flags import OneLineParser, add_config_flags, config_from_args
from imitrl.cli.launch import RankLostError, in_rank, launch, peer_lost, process_group, quiet
from imitrl.limits import MAX_THREADS, Bound
from imitrl.system.heap import collector_paused, freeze_imported
from imitrl.system.threads import DEFAULT_THREADS, set_threads

__all__ = ["COMMANDS", "EXTRAS", "Command", "build_parser", "main", "missing_extra"]


def _load(spec: str) -> Any:
    """``"module:name"`` -> that attribute of the module (imported now)."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class Command:
    """One subcommand: where its config, function and report live, and its help.

    The three are named ``"module:name"`` and imported on first use (:attr:`config`,
    :attr:`run`, :attr:`report`), so that ``imitrl --help`` imports no command and
    ``imitrl COMMAND ...`` imports that command's module alone.
    """

    config_at: str
    """``"module:Class"`` of the frozen dataclass; every field is a flag"""
    run_at: str
    """``"module:function"``, ``function(config) -> results``"""
    report_at: str | None
    """``"module:function"``, results -> lines for stdout (None: the function prints its
    own report)"""
    help: str
    """one line in ``imitrl --help``"""
    description: str
    """the top of ``imitrl COMMAND --help``"""
    epilog: Callable[[], str] | None = None
    """the bottom of ``imitrl COMMAND --help`` (lists of names, its lines kept), built
    only when this command's flags are"""

    @property
    def config(self) -> type:
        """The config dataclass."""
        return _load(self.config_at)

    @property
    def run(self) -> Callable[[Any], Any]:
        """``run(config) -> results``."""
        return _load(self.run_at)

    @property
    def report(self) -> Callable[[Any], list[str]] | None:
        """``report(results) -> lines`` (None: the function prints its own report)."""
        return None if self.report_at is None else _load(self.report_at)


def _names_epilog() -> str:
    """The built-in experts and the registered losses, for ``bc`` / ``dagger`` --help,
    from :mod:`imitrl.jobs.names` (no torch; a test holds it equal to the registry)."""
    from imitrl.jobs.names import EXPERT_ENVS, LOSSES, TABULAR_ENVS, VALUE_ITERATION

    losses = "\n".join(f"  {name:<22} {actions:<10} {summary}" for name, actions, summary in LOSSES)
    experts = ", ".join(f"{name} ({env})" for name, env in EXPERT_ENVS.items())
    experts += (
        f", {VALUE_ITERATION} ({', '.join(TABULAR_ENVS)}, or any toy-text env: the optimal "
        "policy of the env's own model, --env-kwarg map_name=8x8 and the like included)"
    )
    return (
        f"built-in experts (--expert; auto = the one for --env): {experts}\n\n"
        f"losses (--loss): default (resolved for the env: cross_entropy for discrete "
        f"actions, mse for continuous ones (gaussian_nll under imitrl gail and airl, whose "
        f"PPO needs log pi), for_env for images), for_env "
        f"(ActorCritic.for_env's network), or one of\n{losses}"
    )


def _benchmarks_epilog() -> str:
    """The benchmark scripts of the checkout, for ``bench`` --help."""
    from imitrl.jobs.bench import available

    return f"benchmarks: {', '.join(available()) or '(none found)'}"


COMMANDS: dict[str, Command] = {
    "bc": Command(
        "imitrl.jobs.configs:BCJob",
        "imitrl.jobs.bc:run_bc",
        "imitrl.jobs.bc:report",
        "behaviour cloning on expert demonstrations or a dataset",
        "Fit a learner to expert demonstrations (--demos episodes of --expert) or to a "
        "LeRobot/Minari --dataset, evaluate it beside the expert, and write results.json, "
        "a checkpoint (config.json + learner.pt), curves.png and logs/ to --out.",
        _names_epilog,
    ),
    "dagger": Command(
        "imitrl.jobs.configs:DAggerJob",
        "imitrl.jobs.dagger:run_dagger",
        "imitrl.jobs.dagger:report",
        "DAgger: BC, then roll the learner, relabel with the expert, aggregate, refit",
        "Round 0 is behaviour cloning on the demonstrations; each later round refits on "
        "the buffer grown by --episodes-per-round learner episodes labelled by --expert. "
        "Every round is evaluated; results.json, the last learner's checkpoint, curves.png "
        "and logs/ go to --out.",
        _names_epilog,
    ),
    "gail": Command(
        "imitrl.jobs.configs:GAILJob",
        "imitrl.jobs.gail:run_gail",
        "imitrl.jobs.gail:report",
        "GAIL: PPO on a discriminator's reward -log(1 - D(s, a)), from demonstrations",
        "Adversarial imitation (Ho & Ermon 2016) from --demos episodes of --expert or a "
        "LeRobot/Minari --dataset: --total-steps env steps of PPO on the discriminator's "
        "reward; no expert queries after the demonstrations. Writes results.json, a "
        "checkpoint (config.json + learner.pt), curves.png and logs/ to --out.",
        _names_epilog,
    ),
    "airl": Command(
        "imitrl.jobs.configs:AIRLJob",
        "imitrl.jobs.gail:run_airl",
        "imitrl.jobs.gail:report",
        "AIRL: PPO on f(s, a, s') - log pi(a|s), f = g(s) + gamma h(s') - h(s)",
        "Adversarial inverse RL (Fu et al. 2018), state-only reward g, from the same "
        "demonstrations and flags as imitrl gail; outputs as imitrl gail.",
        _names_epilog,
    ),
    "eval": Command(
        "imitrl.jobs.evaluate:EvalJob",
        "imitrl.jobs.evaluate:run_eval",
        "imitrl.jobs.evaluate:report",
        "evaluate a saved learner (--checkpoint) or an expert (--expert)",
        "Mean return and its 95% interval over --eval-episodes episodes on the env seeded "
        "--eval-seed (the defaults reproduce the numbers of imitrl bc/dagger).",
    ),
    "compare": Command(
        "imitrl.jobs.compare:CompareJob",
        "imitrl.jobs.compare:run_compare",
        "imitrl.jobs.compare:report",
        "compare two policies on paired episodes: fixed-size or sequential",
        "Two checkpoints (or expert, random) play episode j from the env seeded --seed + j; "
        "the paired differences of success (or return) give the mean difference, its "
        "interval and the decision, after --episodes pairs or, with --sequential, as soon "
        "as an anytime-valid interval excludes 0.",
    ),
    "bench": Command(
        "imitrl.jobs.bench:BenchJob",
        "imitrl.jobs.bench:run_bench",
        None,
        "run a benchmark script: imitrl bench NAME [args...]",
        "Run benchmarks/NAME.py of the source checkout with the remaining arguments.",
        _benchmarks_epilog,
    ),
    "frozenlake": Command(
        "imitrl.experiments.frozenlake.config:StudyConfig",
        "imitrl.experiments.frozenlake.study:run_study",
        None,
        "reproduce the FrozenLake study (expert, BC, compounding error, DAgger, exercises)",
        "Every experiment of the FrozenLake section on imitrl's pipeline, with the exact value "
        "beside every Monte Carlo estimate. Writes report.txt, results.json and figures to --out.",
    ),
}


THREADS = Bound(1, MAX_THREADS)
"""the values ``--threads`` takes (checked before the command starts)"""


def add_threads_flag(parser: argparse.ArgumentParser) -> None:
    """``--threads N`` (every command): torch's CPU threads while the command runs."""
    parser.add_argument(
        "--threads",
        type=int,
        default=DEFAULT_THREADS,
        metavar="N",
        help="torch's CPU threads while the command runs (bench: the script's starting "
        "count, as OMP_NUM_THREADS); more threads than free cores slow a fit down "
        f"several times: benchmarks/README.md, threads (default: {DEFAULT_THREADS}); "
        f"must be {THREADS.describe()}",
    )


@contextlib.contextmanager
def _script_threads(threads: int) -> Iterator[None]:
    """``OMP_NUM_THREADS=threads`` for the processes started inside (``bench``'s script:
    torch there starts with that many threads), then this process's value back.
    ``threads`` was checked by :func:`main` (:data:`THREADS`)."""
    before = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        yield
    finally:
        if before is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = before


def _bench_threads(args: list[str], threads: int) -> tuple[list[str], int]:
    """``bench``'s script arguments without ``--threads N`` (or ``--threads=N``), and the
    thread count they give (``threads``, the one before NAME, where they give none): the
    remainder took it to the script, which refused it (a review)."""
    kept: list[str] = []
    rest = iter(args)
    for a in rest:
        if a == "--threads" or a.startswith("--threads="):
            value = a.partition("=")[2] if "=" in a else next(rest, "")
            try:
                threads = int(value)
            except ValueError:
                raise ValueError(f"--threads must be {THREADS.describe()}, got {value!r}") from None
        else:
            kept.append(a)
    return kept, threads


def build_parser(flags_for: Collection[str] | None = None) -> argparse.ArgumentParser:
    """The ``imitrl`` argument parser: one subcommand per entry of :data:`COMMANDS`.

    ``flags_for``: the commands that get their flags (and epilog), None = every one;
    the others keep their name and help line. Adding a command's flags imports its
    config's module, so :func:`main` asks only for the command on its command line.
    Every command with its flags also gets ``--threads`` (:func:`add_threads_flag`).
    """
    parser = OneLineParser(prog="imitrl", description="imitrl: imitation learning on TorchRL")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, command in COMMANDS.items():
        if flags_for is not None and name not in flags_for:
            sub.add_parser(name, help=command.help, description=command.description)
        elif command.epilog is not None:  # the lists of names keep their lines
            child = sub.add_parser(
                name,
                help=command.help,
                description=textwrap.fill(command.description, 79),
                epilog=command.epilog(),
                formatter_class=argparse.RawDescriptionHelpFormatter,
            )
            add_config_flags(child, command.config)
            add_threads_flag(child)
        else:
            child = sub.add_parser(name, help=command.help, description=command.description)
            add_config_flags(child, command.config)
            add_threads_flag(child)
    return parser


def _start_torch(threads: int) -> None:
    """Before a command that runs TorchRL: torch's threads (``--threads``), TorchRL's logger."""
    try:
        set_threads(threads)
    except ValueError as err:
        raise ValueError(f"--{err}") from None  # "--threads must be an integer >= 1, ..."
    import torchrl  # noqa: F401  (its import sets the level of its logger: set ours after)

    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines go to stdout


EXTRAS = {
    "pyarrow": "datasets",
    "h5py": "datasets",
    "av": "datasets",
    "huggingface_hub": "hub",
    "ray": "distributed",
    "mujoco": "mujoco",
    "metaworld": "metaworld",
    "Box2D": "box2d",
}
"""the optional package each extra of ``pyproject.toml`` brings -> that extra's name"""


def missing_extra(err: BaseException) -> str:
    """For a module an extra brings and this venv lacks, the install line that adds it
    (``""`` for anything else, or where the message already names the extra)."""
    name = getattr(err, "name", None) or ""
    extra = EXTRAS.get(name.split(".")[0])
    if not isinstance(err, ModuleNotFoundError) or extra is None or f"imitrl[{extra}]" in str(err):
        return ""
    return f" (the {extra!r} extra: pip install 'imitrl[{extra}]')"


def _backend(device: str) -> str:
    """The process group's backend for ``--device``: NCCL on GPUs, gloo on CPUs."""
    from imitrl.system.device import resolve_device

    return "nccl" if resolve_device(device).type == "cuda" else "gloo"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``imitrl`` command; returns the exit status (2 on bad input).

    ``argv`` None (the ``imitrl`` console script, ``python -m imitrl``): the command owns
    its process: it imports its modules with the garbage collector paused and freezes the
    import-time heap before it runs (:mod:`imitrl.system.heap`); a caller that passes
    ``argv`` keeps its collector and heap as they are.
    """
    owns_process = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    # the command is the first word that is not an option (the top level has only -h)
    first = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(flags_for=[first] if first in COMMANDS else []).parse_args(argv)
    command = COMMANDS[args.command]
    try:
        if args.command == "bench":  # --threads after NAME is bench's too (no script has one)
            args.args, args.threads = _bench_threads(list(args.args), args.threads)
        THREADS.check(args.threads, "--threads")
        if args.command == "bench":  # bench starts a script: its threads, and no torch here
            with _script_threads(args.threads):
                results = command.run(config_from_args(command.config, args))
        else:
            # a process the command owns imports without the collector's walks, then
            # freezes what it imported: never walked again (runtime.heap)
            with collector_paused() if owns_process else contextlib.nullcontext():
                _start_torch(args.threads)
                run = command.run  # imports the command's modules
                if owns_process:
                    freeze_imported()
            config = config_from_args(command.config, args)
            nproc = getattr(config, "nproc", 1)
            if nproc > 1 and not in_rank():  # N ranks of this command; this one waits
                return launch(nproc, argv)
            with process_group(_backend(config.device)) if in_rank() else contextlib.nullcontext():
                results = run(config)
    except (ValueError, ImportError) as err:  # bad flags, unknown names, missing extras
        # --nproc: every rank names what it refused (a rank of another machine may hold
        # other files than rank 0), the others with their rank
        who = f"rank {os.environ.get('RANK')}: " if quiet() else ""
        print(f"imitrl {args.command}: {who}{err}{missing_extra(err)}", file=sys.stderr)
        return 2
    except OSError as err:  # a full disk, a read-only folder: named, outputs as they were
        from imitrl.fs.write_errors import DiskFullError, NotWritableError

        if not isinstance(err, DiskFullError | NotWritableError):
            raise
        print(f"imitrl {args.command}: {err}", file=sys.stderr)
        return 1
    except RankLostError as err:  # --nproc: a rank died, the others were stopped
        print(f"imitrl {args.command}: {err}", file=sys.stderr)
        return 1
    except RuntimeError as err:  # a rank whose peer died: the collective fails here
        if not in_rank() or not peer_lost(err):
            raise  # a rank's own error: its traceback
        line = str(err).strip().splitlines()[0][:200]
        rank = os.environ.get("RANK")
        print(f"imitrl {args.command}: rank {rank} lost a peer ({line})", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # outputs are written whole or not at all (see each job)
        print(f"imitrl {args.command}: interrupted", file=sys.stderr)
        return 130
    if command.report is not None and not quiet():
        for line in command.report(results):
            print(line)
    if args.command == "bench":
        code = int(results["returncode"])
        if code < 0:  # the script was killed: the shell's convention, said
            name = signal.Signals(-code).name if -code in signal.valid_signals() else -code
            print(f"imitrl bench: the script was killed by {name}", file=sys.stderr)
            return 128 - code
        return code
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

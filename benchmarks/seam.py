"""What each accelerated piece of the seam buys, whole process, on the commands it serves.

The seam (:mod:`imitrl.runtime.paths`) has a reference path on public TorchRL/torch for
every accelerated piece; ``IMITRL_REFERENCE=piece`` (or ``all``) in a process's
environment puts that piece on its reference path for the whole process. Each piece is
measured on the shipped ``imitrl`` commands that run it:

* ``frozenlake``: ``imitrl frozenlake`` (the study, the README's first command);
* ``dagger_cartpole``: ``imitrl dagger --env CartPole-v1`` (its defaults);
* ``bc_cartpole``: ``imitrl bc --env CartPole-v1`` (its defaults);
* ``gail_pendulum``, ``gail_cartpole``: ``imitrl gail`` on ``peer_gail.py``'s budgets
  (8 lanes, 30,720 / 24,576 env steps, 10 demonstrations; Pendulum at learning rate 1e-3
  and gamma 0.9).

A repeat runs every condition of a command once, in an order shuffled by a fixed seed:
``default`` (every piece accelerated, as shipped), each piece on its reference path
alone, and ``all`` on the reference path. Each run is a fresh process (launch to exit,
measured here) writing to its own ``--out``, at 1 torch thread. Reported per (command,
piece): the median over repeats of ``t(piece on its reference path) / t(default)`` in the
same repeat (the piece's whole-process gain is that ratio minus 1), its range, and
whether the run's ``results.json`` (timings and paths left out) equals the default run's
digit for digit: the reference path must compute the same numbers. A piece is kept where
it buys at least 5% on some command it serves (issue 43).

    python benchmarks/seam.py              # full run (about 40 minutes), refreshes README
    python benchmarks/seam.py --quick      # smoke run: tiny budgets, default and all, two commands, temp dir
"""

from __future__ import annotations

import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import _report
from imitrl.runtime.paths import PIECES

NAME = "seam"
THRESHOLD = 0.05
"""a piece buying less than this on every command it serves is deleted (issue 43)"""
UNTIMED = {"seconds", "timing", "out", "files"}
"""``results.json`` keys that differ between runs of the same numbers"""


@dataclass(frozen=True)
class Command:
    """One shipped command and the pieces it runs."""

    name: str
    argv: tuple[str, ...]
    quick_argv: tuple[str, ...]
    pieces: tuple[str, ...]


_GAIL = ("stepper", "optimizer_step", "zero_grad", "clip_grad_norm", "ppo_loss", "gail_loss")
_FIT = ("stepper", "loss_chain", "optimizer_step", "zero_grad")
COMMANDS = (
    Command("frozenlake", ("frozenlake",), ("frozenlake", "--no-exercises", "--no-irl"), (*_FIT, "table_returns")),
    Command(
        "dagger_cartpole", ("dagger", "--env", "CartPole-v1"),
        ("dagger", "--env", "CartPole-v1", "--rounds", "1", "--steps", "20"), _FIT,
    ),
    Command(
        "bc_cartpole", ("bc", "--env", "CartPole-v1"),
        ("bc", "--env", "CartPole-v1", "--steps", "20"), _FIT,
    ),
    Command(
        "gail_pendulum",
        ("gail", "--env", "Pendulum-v1", "--num-envs", "8", "--total-steps", "30720",
         "--lr", "1e-3", "--gamma", "0.9", "--demos", "10"),
        ("gail", "--env", "Pendulum-v1", "--num-envs", "2", "--total-steps", "128",
         "--rollout-steps", "64", "--demos", "1", "--eval-episodes", "2"),
        _GAIL,
    ),
    Command(
        "gail_cartpole",
        ("gail", "--env", "CartPole-v1", "--num-envs", "8", "--total-steps", "24576",
         "--demos", "10"),
        ("gail", "--env", "CartPole-v1", "--num-envs", "2", "--total-steps", "128",
         "--rollout-steps", "64", "--demos", "1", "--eval-episodes", "2"),
        _GAIL,
    ),
)  # fmt: skip


QUICK_COMMANDS = ("frozenlake", "gail_pendulum")
"""--quick's commands: between them every piece of every command runs on both paths"""


@dataclass(frozen=True)
class Config:
    """The whole run."""

    repeats: int = 5
    """repeats of every (command, condition)"""
    seed: int = 0
    """seed of the order conditions run in within a repeat"""
    commands: tuple[str, ...] = field(default_factory=lambda: tuple(c.name for c in COMMANDS))
    timeout_s: float = 900.0


def numbers(results: object) -> object:
    """``results`` without the keys that change between runs of the same numbers."""
    if isinstance(results, dict):
        return {k: numbers(v) for k, v in results.items() if k not in UNTIMED}
    if isinstance(results, list):
        return [numbers(v) for v in results]
    return results


def imitrl_command() -> list[str]:
    """The ``imitrl`` command of the python running this script (its venv's entry point)."""
    script = Path(sys.executable).parent / "imitrl"
    return [str(script)] if script.exists() else [sys.executable, "-m", "imitrl"]


def run(argv: tuple[str, ...], condition: str, workdir: Path, timeout: float) -> dict:
    """One whole process of ``imitrl argv`` with ``condition``'s pieces on their reference
    path: its wall time and ``results.json``'s numbers."""
    out = Path(tempfile.mkdtemp(prefix=f"{condition}-", dir=workdir))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "IMITRL_REFERENCE": ""}
    if condition != "default":
        env["IMITRL_REFERENCE"] = condition
    cmd = [*imitrl_command(), *argv, "--out", str(out / "run"), "--no-progress", "--threads", "1"]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {done.returncode}:\n{done.stderr[-2000:]}")
    results = json.loads((out / "run" / "results.json").read_text())
    return {"wall": wall, "numbers": numbers(results), "load": os.getloadavg()[0]}


def measure(cfg: Config, quick: bool, workdir: Path) -> list[dict]:
    """Every (command, condition, repeat) run, in the order they ran."""
    rng = random.Random(cfg.seed)
    rows = []
    for command in (c for c in COMMANDS if c.name in cfg.commands):
        argv = command.quick_argv if quick else command.argv
        # --quick: the smoke run, every piece on its reference path at once only (each
        # piece's own digits are tests/runtime/test_paths.py's)
        conditions = ["default", "all"] if quick else ["default", *command.pieces, "all"]
        for repeat in range(cfg.repeats):
            order = conditions[:]
            rng.shuffle(order)
            for condition in order:
                r = run(argv, condition, workdir, cfg.timeout_s)
                print(f"{command.name} #{repeat} {condition}: {r['wall']:.2f} s (load "
                      f"{r['load']:.2f})", file=sys.stderr, flush=True)  # fmt: skip
                rows.append(
                    {"command": command.name, "condition": condition, "repeat": repeat, **r}
                )
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Per (command, condition other than default): the paired ratios to the default."""
    out = []
    for command in dict.fromkeys(r["command"] for r in rows):
        mine = [r for r in rows if r["command"] == command]
        base = {r["repeat"]: r for r in mine if r["condition"] == "default"}
        for condition in dict.fromkeys(r["condition"] for r in mine):
            if condition == "default":
                continue
            runs = [r for r in mine if r["condition"] == condition]
            ratios = [r["wall"] / base[r["repeat"]]["wall"] for r in runs]
            out.append({
                "command": command,
                "piece": condition,
                "ratio_median": statistics.median(ratios),
                "ratio_min": min(ratios),
                "ratio_max": max(ratios),
                "default_s": statistics.median(b["wall"] for b in base.values()),
                "reference_s": statistics.median(r["wall"] for r in runs),
                "same_numbers": all(r["numbers"] == base[r["repeat"]]["numbers"] for r in runs),
                "load": [round(r["load"], 2) for r in runs],
            })  # fmt: skip
    return out


def verdicts(summary: list[dict]) -> dict[str, dict]:
    """Per piece: its best whole-process gain over the commands it serves, and whether it
    clears :data:`THRESHOLD`."""
    out: dict[str, dict] = {}
    for piece in PIECES:
        mine = [s for s in summary if s["piece"] == piece]
        if not mine:
            continue
        best = max(mine, key=lambda s: s["ratio_median"])
        gain = best["ratio_median"] - 1
        out[piece] = {"best_gain": gain, "on": best["command"], "keep": gain >= THRESHOLD}
    return out


def markdown(summary: list[dict], kept: dict[str, dict], cfg: Config, load: list[float]) -> str:
    header = ["command", "piece on its reference path", "default s", "reference s",
              "gain (median [range])", "same numbers"]  # fmt: skip
    rows = [
        [s["command"], s["piece"], f"{s['default_s']:.2f}", f"{s['reference_s']:.2f}",
         f"{s['ratio_median'] - 1:+.1%} [{s['ratio_min'] - 1:+.1%}, {s['ratio_max'] - 1:+.1%}]",
         "yes" if s["same_numbers"] else "**no**"]
        for s in summary
    ]  # fmt: skip
    verdict = [[p, f"{v['best_gain']:+.1%}", v["on"], "kept" if v["keep"] else "**below 5%**"]
               for p, v in kept.items()]  # fmt: skip
    return "\n\n".join([
        f"Whole-process wall time of each shipped command with one piece on its reference "
        f"path (`IMITRL_REFERENCE=piece`), over the same command as shipped, paired within "
        f"each of {cfg.repeats} repeats (shuffled order, 1 torch thread; load average "
        f"{min(load):.2f}-{max(load):.2f} across the runs). Gain: reference time / default "
        f"time - 1.",
        _report.table(header, rows),
        "Each piece's best gain over the commands it serves (the 5% rule of issue 43):",
        _report.table(["piece", "best gain", "on", "verdict"], verdict),
    ])  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = _report.parser(__doc__)
    parser.add_argument("--repeats", type=int, default=None, help="default 5; 1 with --quick")
    parser.add_argument("--commands", nargs="+", default=None,
                        choices=[c.name for c in COMMANDS])  # fmt: skip
    args = parser.parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    # --quick: one command per kind of piece (the fit's and GAIL's) unless named
    commands = args.commands or (QUICK_COMMANDS if args.quick else None)
    cfg = Config(
        repeats=args.repeats or (1 if args.quick else 5),
        **({"commands": tuple(commands)} if commands else {}),
    )
    with tempfile.TemporaryDirectory(prefix="seam-") as tmp:
        rows = measure(cfg, args.quick, Path(tmp))
    summary = summarise(rows)
    kept = verdicts(summary)
    load = [r["load"] for r in rows]
    payload = {
        "config": {**cfg.__dict__, "quick": args.quick},
        "summary": summary,
        "verdicts": kept,
        "runs": [{k: v for k, v in r.items() if k != "numbers"} for r in rows],
    }
    path = _report.write(NAME, payload, markdown(summary, kept, cfg, load), out_dir=out_dir)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

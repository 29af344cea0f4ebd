"""``peer_gail.py``'s summary: ratios imitrl / imitation per seed under each protocol."""

from __future__ import annotations

import statistics

import _report
from _peer_imitation.report import install_line
from _peer_imitation.tasks import PROCESS_LABELS

NAME = "peer_gail"
PHASES = ("wall", "imports", "setup", "train", "evaluation", "outside")
"""``outside``: the whole process less the child's own clock (interpreter start and exit)"""
TARGET = 0.5
"""issue 31: imitrl's whole-process wall time at most half imitation's"""


def _seconds(run: dict, key: str) -> float | None:
    """``key``'s seconds in ``run``; None where it has none (the command reports only
    its wall time and its job's clock)."""
    if key == "wall":
        return run["wall"]
    phases = run["phases"]
    if key == "outside":
        return run["wall"] - phases["in_process"] if "in_process" in phases else None
    return phases.get(key)


def row_label(protocol: str | None, process: str) -> str:
    """A row's name within its task: the protocol (a plain script's row), then the
    process where it is not one (``own, collector trick``, ``own, command as shipped``)."""
    base = protocol or "own"
    return base if process == "plain" else f"{base}, {PROCESS_LABELS[process]}"


def _phase(ours: dict[int, dict], peer: dict[int, dict], key: str) -> dict:
    """One phase of one row: seconds per seed of both sides, the ratios of the seeds
    where both have it, and their median."""
    mine = {s: _seconds(ours[s], key) for s in sorted(ours)}
    theirs = {s: _seconds(peer[s], key) for s in sorted(peer)}
    ratios = [mine[s] / theirs[s] for s in mine if s in theirs and None not in (mine[s], theirs[s])]
    return {
        "imitrl": [x for x in mine.values() if x is not None],
        "imitation": [x for x in theirs.values() if x is not None],
        "ratios": ratios,
        "median_ratio": statistics.median(ratios) if ratios else None,
    }


def _row(ours: dict[int, dict], peer: dict[int, dict], protocol, process: str) -> dict:
    """One row's summary: imitrl's runs of one (protocol, process), each paired with
    imitation's run of the same seed."""
    seeds = sorted(s for s in ours if s in peer)
    phases = {key: _phase(ours, peer, key) for key in PHASES}
    med = phases["wall"]["median_ratio"]
    return {
        "protocol": protocol,
        "process": process,
        "headline": process == "plain" and (protocol or "own") == "own",
        "seeds": seeds,
        "phases": phases,
        "returns": {
            "imitrl": [ours[s]["returns"]["final"] for s in sorted(ours)],
            "imitation": [peer[s]["returns"]["final"] for s in sorted(peer)],
        },
        "wall_met": None if med is None else med <= TARGET,
        "wall_met_each_seed": (
            all(r <= TARGET for r in phases["wall"]["ratios"]) if seeds else None
        ),
        "returns_met": (
            all(ours[s]["returns"]["final"] >= peer[s]["returns"]["final"] for s in seeds)
            if seeds else None
        ),
    }  # fmt: skip


def summarise(runs: list[dict]) -> dict:
    """Per task, one row per imitrl (protocol, process) (:func:`row_label`; results
    without ``process`` read as plain scripts): seconds per seed, ratios to imitation's
    run of the same seed (imitation runs once per seed, every row pairs with it), their
    median, the returns per seed, and whether the target is met. The headline row is
    ``own``, the plain script."""
    out: dict = {}
    for task in dict.fromkeys(r["task"] for r in runs):
        mine = [r for r in runs if r["task"] == task]
        peer = {r["seed"]: r for r in mine if r["library"] == "imitation"}
        rows: dict[str, tuple] = {}
        for r in mine:
            if r["library"] == "imitrl":
                process = r.get("process", "plain")
                key = row_label(r["protocol"], process)
                rows.setdefault(key, (r["protocol"], process, {}))[2][r["seed"]] = r
        out[task] = {key: _row(ours, peer, p, proc) for key, (p, proc, ours) in rows.items()}
    return out


def _per_seed(xs: list[float], digits: int = 2) -> str:
    return " / ".join(f"{x:.{digits}f}" for x in xs) if xs else "-"


def _yes(met) -> str:
    return "" if met is None else ("yes" if met else "**no**")


def table(summary: dict) -> str:
    """One line per (task, row): wall seconds and ratios per seed, the training phase's
    ratios, the process's start and exit, the returns, and the target's verdicts."""
    rows = []
    for task, by in summary.items():
        for name, s in by.items():
            wall = s["phases"]["wall"]
            train, outside = s["phases"]["train"], s["phases"]["outside"]
            med = wall["median_ratio"]
            rows.append([
                task, f"**{name}**" if s.get("headline") else name,
                _per_seed(wall["imitrl"], 1), _per_seed(wall["imitation"], 1),
                _per_seed(wall["ratios"]), "-" if med is None else f"{med:.2f}",
                _per_seed(train["ratios"]),
                _per_seed(outside["imitrl"], 1), _per_seed(outside["imitation"], 1),
                _per_seed(s["returns"]["imitrl"], 1), _per_seed(s["returns"]["imitation"], 1),
                _yes(s["wall_met"]), _yes(s.get("wall_met_each_seed")), _yes(s["returns_met"]),
            ])  # fmt: skip
    header = [
        "task", "protocol, process", "imitrl wall s", "imitation wall s",
        "wall ratio per seed", "median wall ratio", "train ratio per seed",
        "imitrl start + exit s", "imitation start + exit s",
        "imitrl return", "imitation return",
        f"median wall <= {TARGET}", f"wall <= {TARGET} each seed",
        "return >= imitation's (each seed)",
    ]  # fmt: skip
    return _report.table(header, rows)


PLAN_WORDS = {
    ("imitrl", "own", "plain"): "imitrl `own`",
    ("imitation", None, "plain"): "imitation",
    ("imitrl", "matched", "plain"): "imitrl `matched`",
    ("imitrl", "own", "collector_trick"): "imitrl `own` with the collector trick",
    ("imitrl", "own", "command"): "the shipped `imitrl gail` / `imitrl airl` command",
}
"""how the head names each job of ``peer_gail.PLAN``"""


def _plan_line(plan: list | None) -> str:
    """``per (task, seed) N fresh processes in turn (...)``, from the config's plan
    (results from before it: the three processes they ran)."""
    if plan is None:
        return "three fresh processes in turn (imitrl `own`, imitation, imitrl `matched`)"
    words = [PLAN_WORDS.get(tuple(job), " ".join(str(x) for x in job)) for job in plan]
    return f"{len(words)} fresh processes in turn ({', '.join(words)})"


def _process_note(plan: list | None) -> str:
    """What the head says of the processes: plain scripts and the extra rows, or, for
    results from before the plan was recorded, what their imitrl children did."""
    if plan is None:
        return (
            "These results predate issue 43: every imitrl child then paused and froze the "
            "garbage collector at import as the `imitrl` command does (not recorded)."
        )
    return (
        "Every script, both libraries', is a plain Python script as a user runs it; the "
        "headline is **own**, imitrl's plain script. `own, collector trick`: the same "
        "script with what the `imitrl` command does in the process it owns (imports with "
        "the garbage collector paused, the import-time heap frozen); `own, command as "
        "shipped`: the `imitrl gail` / `imitrl airl` command with the `own` settings, "
        "whole, with its own evaluations of the expert and the untrained learner, logger, "
        "results.json, checkpoint and curves.png (its return evaluated on its own lanes; "
        "no phases)."
    )


def markdown(raw: dict) -> str:
    cfg, ours, peer = raw["config"], raw["imitrl_versions"], raw.get("peer_versions")
    if peer:
        versions = ", ".join(
            f"{n} {peer.get(n, '-')}"
            for n in ("imitation", "stable-baselines3", "gymnasium", "torch")
        )
    else:
        versions = "not run (--quick: imitrl's side only)"
    ours = ", ".join(f"{n} {ours.get(n, '-')}" for n in ("torch", "torchrl", "tensordict"))
    head = (
        f"{cfg['seeds']} seed(s) per task; per (task, seed) {_plan_line(cfg.get('plan'))}, "
        f"1 torch thread each; total {raw['wall_seconds']:.0f} s. imitrl: {ours}. Peer "
        f"venv: {versions}. Ratios are imitrl / imitation of the same seed, whole process "
        "(wall) and the training phase alone (train); **protocol** `own`: each library at "
        "its own recommended settings; `matched`: imitrl with imitation's hyperparameters "
        "(see the script's docstring). "
        + _process_note(cfg.get("plan"))
        + (f" Bytecode: {cfg['bytecode']}." if cfg.get("bytecode") else "")
        + install_line(cfg.get("imitrl_install"))
    )
    return "\n\n".join([head, table(raw["summary"])])

"""``peer_imitation.py``'s summary: per-pair ratios and medians over seeds, the tables."""

from __future__ import annotations

import statistics

import _report
from _peer_imitation.tasks import PROCESS_LABELS

NAME = "peer_imitation"

PHASES = (
    ("wall", "whole process", 0.5),
    ("imports", "imports", None),
    ("setup", "setup (envs, expert, demonstrations)", None),
    ("bc", "BC", 0.33),
    ("dagger", "DAgger (collection + fits)", 0.33),
    ("dagger_collect", "- collection", None),
    ("dagger_fit", "- fits", None),
    ("evaluation", "evaluation", 0.33),
)
"""(key, label, target ratio imitrl / imitation or None): ``wall`` is measured by the
parent from launch to exit, the others by the child"""


def _median(xs: list[float]) -> float | None:
    return statistics.median(xs) if xs else None


def _seconds(run: dict, key: str) -> float:
    return run["wall"] if key == "wall" else run["phases"][key]


def _phase(by: dict[str, dict[int, dict]], key: str, target: float | None) -> dict:
    """One phase: seconds per seed of each library, ratios imitrl / imitation of the
    seeds both ran, their median, and whether it meets ``target``."""
    sec = {lib: [_seconds(by[lib][s], key) for s in sorted(by[lib])] for lib in by}
    paired = [s for s in sorted(by["imitrl"]) if s in by["imitation"]]
    ratios = [_seconds(by["imitrl"][s], key) / _seconds(by["imitation"][s], key) for s in paired]
    med = _median(ratios)
    return {
        "seconds": sec,
        "median_seconds": {lib: _median(v) for lib, v in sec.items()},
        "ratios": ratios,
        "median_ratio": med,
        "target": target,
        "met": None if target is None or med is None else med <= target,
    }


def _per_stage(by: dict[str, dict[int, dict]], field: str) -> dict:
    """``{library: {"bc": [per seed], "final": [per seed]}}`` of ``returns`` or ``exact_success``."""
    return {
        lib: {
            stage: [by[lib][s][field][stage] for s in sorted(by[lib])] for stage in ("bc", "final")
        }
        for lib in by
    }


def process_of(run: dict) -> str:
    """How a run's process ran (``tasks.PROCESSES``): results from before the field read
    as ``plain``, and so does every imitation run (its children are always plain)."""
    return "plain" if run["library"] == "imitation" else run.get("process", "plain")


def label(run: dict) -> str:
    """A run's row label: its task and protocol (``cartpole, matched``), and for an
    imitrl run that was not a plain script its process too (``cartpole, own, collector
    trick``); imitation's runs carry the label of the plain row they pair with."""
    protocol = run.get("protocol")
    base = run["task"] if protocol is None else f"{run['task']}, {protocol}"
    process = process_of(run)
    return base if process == "plain" else f"{base}, {PROCESS_LABELS[process]}"


def _pairs(runs: list[dict]) -> dict[str, dict[str, dict[int, dict]]]:
    """Row label -> ``{library: {seed: run}}``: each imitrl (task, protocol, process)
    with imitation's runs of the same task and protocol (a collector-trick row shares
    imitation's runs with the plain row of its protocol). Rows in the order imitrl's
    runs first appear (imitation's alone where imitrl has none)."""
    peers = {}
    for r in runs:
        if r["library"] == "imitation":
            peers.setdefault(label(r), {})[r["seed"]] = r
    rows: dict[str, dict[str, dict[int, dict]]] = {}
    for r in runs:
        if r["library"] == "imitrl":
            plain = label({**r, "process": "plain"})
            row = rows.setdefault(label(r), {"imitrl": {}, "imitation": peers.get(plain, {})})
            row["imitrl"][r["seed"]] = r
    for name, by_seed in peers.items():
        rows.setdefault(name, {"imitrl": {}, "imitation": by_seed})
    return rows


def summarise(runs: list[dict], references: dict[str, list[float]]) -> dict:
    """Per row (task, protocol and, beside the plain scripts, imitrl's process: see
    :func:`label`): every phase's per-seed seconds of both libraries, per-pair ratios,
    medians; the BC and final returns per seed (FrozenLake: also the exact success of
    each greedy policy, on which it is judged); whether each target is met."""
    out = {}
    for row, by in _pairs(runs).items():
        first = next(iter({**by["imitation"], **by["imitrl"]}.values()))
        returns = _per_stage(by, "returns")
        tabular = bool(by["imitrl"]) and all("exact_success" in r for r in by["imitrl"].values())
        exact = _per_stage(by, "exact_success") if tabular else None
        ours, theirs = ((exact or returns)[lib]["final"] for lib in ("imitrl", "imitation"))
        process = process_of(next(iter(by["imitrl"].values()), first))
        out[row] = {
            "task": first["task"],
            "protocol": first.get("protocol"),
            "process": process,
            "headline": process == "plain" and (first.get("protocol") or "own") == "own",
            "seeds": sorted(by["imitrl"]),
            "phases": {key: _phase(by, key, target) for key, _, target in PHASES},
            "returns": returns,
            "exact_success": exact,
            "expert": references.get(first["task"]),
            "rows": {lib: [by[lib][s]["rows"] for s in sorted(by[lib])] for lib in by},
            "gc_frozen": [by["imitrl"][s].get("gc_frozen") for s in sorted(by["imitrl"])],
            "process_recorded": all("process" in r for r in by["imitrl"].values()),
            "returns_met": (
                bool(_median(ours) >= _median(theirs) - 1e-9) if ours and theirs else None
            ),
        }
    return out


# ------------------------------------------------------------------------- tables
def _s(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def _per_seed(xs: list[float], digits: int) -> str:
    return " / ".join(f"{x:.{digits}f}" for x in xs) if xs else "-"


def _yes(met: bool | None) -> str:
    return "" if met is None else ("yes" if met else "**no**")


PHASE_HEADER = ["task", "phase", "imitrl s", "imitation s", "ratio per seed", "median ratio"]
RETURN_HEADER = ["task", "expert", "imitrl BC", "imitation BC", "imitrl final", "imitation final"]


def phase_table(summary: dict) -> str:
    """Median seconds of both libraries and the ratios, phase by phase, with the targets."""
    rows = []
    for task, s in summary.items():
        for key, label, _ in PHASES:
            p = s["phases"][key]
            med, target = p["median_seconds"], p["target"]
            rows.append(
                [
                    task,
                    label,
                    _s(med["imitrl"]),
                    _s(med["imitation"]),
                    _per_seed(p["ratios"], 2),
                    _s(p["median_ratio"]),
                    "" if target is None else f"<= {target}",
                    _yes(p["met"]),
                ]
            )
    return _report.table([*PHASE_HEADER, "target", "met"], rows)


def _return_row(label: str, expert: list, per_lib: dict, digits: int, met) -> list[str]:
    cells = [per_lib[lib][stage] for stage in ("bc", "final") for lib in ("imitrl", "imitation")]
    return [label, _per_seed(expert, digits), *(_per_seed(c, digits) for c in cells), _yes(met)]


def returns_table(summary: dict) -> str:
    """BC and final returns per seed of both libraries (FrozenLake: a second row of the
    exact success of each greedy policy, on which it is judged)."""
    rows = []
    for task, s in summary.items():
        expert, exact = s["expert"] or [], s["exact_success"]
        if exact is None:
            rows.append(_return_row(task, expert, s["returns"], 1, s["returns_met"]))
            continue
        rows.append(_return_row(task, [], s["returns"], 3, None))
        label = f"{task} (exact success of the greedy policy)"
        rows.append(_return_row(label, expert, exact, 4, s["returns_met"]))
    return _report.table([*RETURN_HEADER, "imitrl >= imitation (median)"], rows)


def install_line(install: dict | None) -> str:
    """One sentence for a report: which venv ran imitrl, and its extras."""
    if not install:
        return ""
    extras = install["optional_packages"]
    held = f"with {', '.join(extras)} installed" if extras else "imitrl's requirements alone"
    return f" imitrl's children ran on `{install['python']}` ({held})."


def process_note(summary: dict) -> str:
    """What the head says of the processes: plain scripts on both sides, the headline
    rows, and the collector-trick rows where the summary has any; for results that
    predate the field (read as plain), what their imitrl children did instead."""
    if not all(s.get("process_recorded", False) for s in summary.values()):
        return (
            "These results do not record how imitrl's children ran their processes: they "
            "predate issue 43, when every imitrl child paused and froze the garbage "
            "collector at import as the `imitrl` command does; read here as plain rows."
        )
    note = (
        "Both libraries' children are plain Python scripts, as a user runs them (the "
        "garbage collector as Python starts it); the headline ratios are the `own` rows."
    )
    trick = [s for s in summary.values() if s.get("process") == "collector_trick"]
    if trick:
        frozen = [n for s in trick for n in s.get("gc_frozen", []) if n is not None]
        held = f", {statistics.median(frozen):,.0f} objects frozen" if frozen else ""
        note += (
            " The row `<task>, own, collector trick` is imitrl's `own` run again with what "
            "the `imitrl` command does in the process it owns (imports with the collector "
            f"paused, the import-time heap frozen out of its walks{held}), paired with "
            "imitation's `own` run of the same seed: what the trick is worth, not what a "
            "script gets."
        )
    return note


def markdown(raw: dict) -> str:
    """The README block: how it was run, the phase table, the returns table."""
    cfg, ours, peer = raw["config"], raw["imitrl_versions"], raw.get("peer_versions")
    if peer:
        names = ("imitation", "stable-baselines3", "gymnasium", "torch")
        versions = ", ".join(f"{n} {peer.get(n, '-')}" for n in names)
    else:
        versions = "not run (--quick: imitrl's side only)"
    ours = ", ".join(
        f"{n} {ours.get(n, '-')}" for n in ("torch", "torchrl", "tensordict", "gymnasium")
    )
    head = (
        f"{cfg['seeds']} seed(s) per task, each (task, library, protocol, process, seed) a "
        "fresh process, one after another, 1 torch thread each; total "
        f"{raw['wall_seconds']:.0f} s. imitrl: {ours}. Peer venv: {versions}. Seconds are "
        "medians over seeds; ratios imitrl / imitation per seed, then their median. "
        + process_note(raw["summary"])
    )
    if cfg.get("imitrl_loss", "default") != "default":
        head += f" imitrl's learner: the `{cfg['imitrl_loss']}` registry entry."
    if cfg.get("bytecode"):
        head += f" Bytecode: {cfg['bytecode']}."
    head += install_line(cfg.get("imitrl_install"))
    returns = (
        "**Returns per seed** (greedy; FrozenLake: the mean return = the success rate over "
        "the evaluation episodes, then the exact success probability in 100 steps)"
    )
    return "\n\n".join(
        [
            head,
            _report.section(
                "**Wall time by phase** (targets: issue 16)", phase_table(raw["summary"])
            ),
            _report.section(returns, returns_table(raw["summary"])),
        ]
    )

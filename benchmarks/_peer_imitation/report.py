"""``peer_imitation.py``'s summary: per-pair ratios and medians over seeds, the tables."""

from __future__ import annotations

import statistics

import _report

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


def label(run: dict) -> str:
    """A run's row label: its task and protocol (``cartpole, matched``)."""
    protocol = run.get("protocol")
    return run["task"] if protocol is None else f"{run['task']}, {protocol}"


def summarise(runs: list[dict], references: dict[str, list[float]]) -> dict:
    """Per task: every phase's per-seed seconds of both libraries, per-pair ratios,
    medians; the BC and final returns per seed (FrozenLake: also the exact success of
    each greedy policy, on which it is judged); whether each target is met."""
    out = {}
    for task in dict.fromkeys(label(r) for r in runs):
        by = {
            lib: {r["seed"]: r for r in runs if label(r) == task and r["library"] == lib}
            for lib in ("imitrl", "imitation")
        }
        returns = _per_stage(by, "returns")
        tabular = all("exact_success" in r for r in by["imitrl"].values())
        exact = _per_stage(by, "exact_success") if tabular else None
        ours, theirs = ((exact or returns)[lib]["final"] for lib in ("imitrl", "imitation"))
        out[task] = {
            "seeds": sorted(by["imitrl"]),
            "phases": {key: _phase(by, key, target) for key, _, target in PHASES},
            "returns": returns,
            "exact_success": exact,
            "expert": references.get(task.split(",")[0]),
            "rows": {lib: [by[lib][s]["rows"] for s in sorted(by[lib])] for lib in by},
            "returns_met": bool(_median(ours) >= _median(theirs) - 1e-9) if theirs else None,
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
        f"{cfg['seeds']} seed(s) per task, each (task, library, seed) a fresh process, the "
        "libraries alternating (imitrl, imitation, imitrl, ...), 1 torch thread each; total "
        f"{raw['wall_seconds']:.0f} s. imitrl: {ours}. Peer venv: {versions}. Seconds are "
        "medians over seeds; ratios imitrl / imitation per seed, then their median."
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

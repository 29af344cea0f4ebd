"""``peer_gail.py``'s summary: ratios imitrl / imitation per seed under each protocol."""

from __future__ import annotations

import statistics

import _report
from _peer_imitation.report import install_line

NAME = "peer_gail"
PHASES = ("wall", "imports", "setup", "train", "evaluation", "outside")
"""``outside``: the whole process less the child's own clock (interpreter start and exit)"""
TARGET = 0.5
"""issue 31: imitrl's whole-process wall time at most half imitation's"""


def _seconds(run: dict, key: str) -> float:
    if key == "outside":
        return run["wall"] - run["phases"]["in_process"]
    return run["wall"] if key == "wall" else run["phases"][key]


def summarise(runs: list[dict]) -> dict:
    """Per task and protocol: seconds per seed, ratios to imitation's run of the same
    seed, their median, the returns per seed, and whether the target is met."""
    out: dict = {}
    for task in dict.fromkeys(r["task"] for r in runs):
        mine = [r for r in runs if r["task"] == task]
        peer = {r["seed"]: r for r in mine if r["library"] == "imitation"}
        out[task] = {}
        for protocol in dict.fromkeys(r["protocol"] for r in mine if r["library"] == "imitrl"):
            ours = {
                r["seed"]: r for r in mine if r["library"] == "imitrl" and r["protocol"] == protocol
            }
            seeds = sorted(s for s in ours if s in peer)
            phases = {}
            for key in PHASES:
                ratios = [_seconds(ours[s], key) / _seconds(peer[s], key) for s in seeds]
                phases[key] = {
                    "imitrl": [_seconds(ours[s], key) for s in sorted(ours)],
                    "imitation": [_seconds(peer[s], key) for s in sorted(peer)],
                    "ratios": ratios,
                    "median_ratio": statistics.median(ratios) if ratios else None,
                }
            mine_r = [ours[s]["returns"]["final"] for s in sorted(ours)]
            peer_r = [peer[s]["returns"]["final"] for s in sorted(peer)]
            med = phases["wall"]["median_ratio"]
            out[task][protocol] = {
                "seeds": seeds,
                "phases": phases,
                "returns": {"imitrl": mine_r, "imitation": peer_r},
                "wall_met": None if med is None else med <= TARGET,
                "wall_met_each_seed": (
                    all(r <= TARGET for r in phases["wall"]["ratios"]) if seeds else None
                ),
                "returns_met": (
                    all(ours[s]["returns"]["final"] >= peer[s]["returns"]["final"] for s in seeds)
                    if seeds else None
                ),
            }  # fmt: skip
    return out


def _per_seed(xs: list[float], digits: int = 2) -> str:
    return " / ".join(f"{x:.{digits}f}" for x in xs) if xs else "-"


def _yes(met) -> str:
    return "" if met is None else ("yes" if met else "**no**")


def table(summary: dict) -> str:
    rows = []
    for task, by in summary.items():
        for protocol, s in by.items():
            wall = s["phases"]["wall"]
            train, outside = s["phases"]["train"], s["phases"]["outside"]
            med = wall["median_ratio"]
            rows.append([
                task, protocol,
                _per_seed(wall["imitrl"], 1), _per_seed(wall["imitation"], 1),
                _per_seed(wall["ratios"]), "-" if med is None else f"{med:.2f}",
                _per_seed(train["ratios"]),
                _per_seed(outside["imitrl"], 1), _per_seed(outside["imitation"], 1),
                _per_seed(s["returns"]["imitrl"], 1), _per_seed(s["returns"]["imitation"], 1),
                _yes(s["wall_met"]), _yes(s.get("wall_met_each_seed")), _yes(s["returns_met"]),
            ])  # fmt: skip
    header = [
        "task", "protocol", "imitrl wall s", "imitation wall s", "wall ratio per seed",
        "median wall ratio", "train ratio per seed", "imitrl start + exit s",
        "imitation start + exit s",
        "imitrl return", "imitation return",
        f"median wall <= {TARGET}", f"wall <= {TARGET} each seed",
        "return >= imitation's (each seed)",
    ]  # fmt: skip
    return _report.table(header, rows)


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
        f"{cfg['seeds']} seed(s) per task; per (task, seed) three fresh processes in turn "
        "(imitrl `own`, imitation, imitrl `matched`), 1 torch thread each; total "
        f"{raw['wall_seconds']:.0f} s. imitrl: {ours}. Peer venv: {versions}. Ratios are "
        "imitrl / imitation of the same seed, whole process (wall) and the training phase "
        "alone (train); **protocol** `own`: each library at its own recommended settings; "
        "`matched`: imitrl with imitation's hyperparameters (see the script's docstring)."
        + (f" Bytecode: {cfg['bytecode']}." if cfg.get("bytecode") else "")
        + install_line(cfg.get("imitrl_install"))
    )
    return "\n\n".join([head, table(raw["summary"])])

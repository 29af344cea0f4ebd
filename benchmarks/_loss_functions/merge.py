"""Runs of disjoint cells combined into one result: a loss added without re-running the rest.

Every cell's digits depend on its seed alone (``run.py``), so a run of new losses on
the same tasks, seeds and protocols completes an earlier run exactly as if both had
run together. :func:`merge` refuses what would not: different seeds, a task whose
protocol or definition differs, references (expert and random scores) that differ, or
a cell present in both. The merged result names every run it came from, its command
and wall time (``config["parts"]``).
"""

from __future__ import annotations

from typing import Any

__all__ = ["join_cells", "merge", "with_defaults"]


def with_defaults(protocol: dict) -> dict:
    """A recorded protocol with the fields it predates filled with their defaults (a run
    recorded before a field existed trained as its default says)."""
    from dataclasses import MISSING, asdict, fields

    from _loss_functions.tasks import LearnerSettings, Protocol
    from imitrl.algorithms import BCConfig

    out = {f.name: f.default for f in fields(Protocol) if f.default is not MISSING}
    out.update(protocol)
    out["bc"] = {**asdict(BCConfig()), **protocol.get("bc", {})}
    out["learner"] = {
        **{
            k: (list(v) if isinstance(v, tuple) else v)
            for k, v in asdict(LearnerSettings()).items()
        },
        **protocol.get("learner", {}),
    }
    return out


def join_cells(runs: list[dict], keep=lambda task: True) -> tuple[list[dict], list[dict]]:
    """Every run's rows and references whose task ``keep`` accepts, each once (ValueError
    where two runs measured a reference with other digits, or ran the same cell: the code
    changed between them, or the cells overlap). The Meta-World suites' merges."""
    rows, refs, cells = [], {}, set()
    for k, part in enumerate(runs):
        for ref in part["references"]:
            key = (ref["task"], ref["policy"], ref["seed"])
            if keep(ref["task"]) and refs.setdefault(key, ref) != ref:
                raise ValueError(f"run {k} measured another {key} reference: the code changed")
        for row in part["rows"]:
            if not keep(row["task"]):
                continue
            if _cell(row) in cells:
                raise ValueError(f"run {k} repeats the cell {_cell(row)}")
            cells.add(_cell(row))
            rows.append(row)
    return rows, list(refs.values())


def _cell(row: dict) -> tuple:
    return (row["task"], row["loss"], row["seed"], row["algorithm"])


def _check_seeds(rows: list[dict], seeds: int) -> None:
    """ValueError naming the first (task, loss, algorithm) whose rows do not hold the
    ``seeds`` seeds the runs' configs say (a hostile review: a part whose rows held 3
    seeds merged under a header of 5, its intervals silently on 3)."""
    held: dict[tuple, set] = {}
    for row in rows:
        held.setdefault((row["task"], row["loss"], row["algorithm"]), set()).add(row["seed"])
    for cell, have in held.items():
        if len(have) != seeds:
            raise ValueError(f"{cell} has seeds {sorted(have)}; the runs' configs say {seeds}")


def merge(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One raw result (``run.py``'s, with ``config``) from ``runs`` (ValueError naming
    the first disagreement)."""
    if len(runs) < 2:
        raise ValueError("merge needs at least two results")
    first = runs[0]
    seeds = {r["config"]["seeds"] for r in runs}
    if len(seeds) != 1:
        raise ValueError(f"the runs used different numbers of seeds: {sorted(seeds)}")
    if len({bool(r["config"].get("quick")) for r in runs}) != 1:
        raise ValueError("a quick run and a full run cannot be merged")
    torches = {r.get("machine", {}).get("torch") for r in runs} - {None}
    if len(torches) > 1:
        raise ValueError(f"the runs used different torch versions: {sorted(torches)}")
    out = {
        "rows": [],
        "references": [],
        "protocols": {},
        "tasks": {},
        "losses": {},
        "wall_seconds": 0.0,
    }
    refs: dict[tuple, float] = {}
    cells: set[tuple] = set()
    for k, run in enumerate(runs):
        for name, protocol in run["protocols"].items():
            protocol = with_defaults(protocol)  # fields added since an older run: defaults
            if out["protocols"].setdefault(name, protocol) != protocol:
                raise ValueError(f"run {k} trained task {name!r} with another protocol")
        for name, definition in run.get("tasks", {}).items():
            if "protocol" in definition:
                definition = {**definition, "protocol": with_defaults(definition["protocol"])}
            if out["tasks"].setdefault(name, definition) != definition:
                raise ValueError(f"run {k} defines task {name!r} differently")
        for ref in run["references"]:
            key = (ref["task"], ref["policy"], ref["seed"])
            if key in refs and refs[key] != ref["score"]:
                raise ValueError(f"run {k} measured another {key} reference: the code changed")
            if key not in refs:
                refs[key] = ref["score"]
                out["references"].append(ref)
        for row in run["rows"]:
            if _cell(row) in cells:
                raise ValueError(f"cell {_cell(row)} is in more than one run")
            cells.add(_cell(row))
            out["rows"].append(row)
        out["losses"].update(run.get("losses", {}))
        out["wall_seconds"] += run["wall_seconds"]
    _check_seeds(out["rows"], next(iter(seeds)))
    config = dict(first["config"])
    config["tasks"] = list(dict.fromkeys(t for r in runs for t in r["config"]["tasks"]))
    config["losses"] = None
    config["jobs"] = max(r["config"]["jobs"] for r in runs)
    config["parts"] = [
        {
            "command": r["config"].get("command"),
            "wall_seconds": r["wall_seconds"],
            "torch": r.get("machine", {}).get("torch"),
            "rows": len(r["rows"]),
        }
        for r in runs
    ]
    config["command"] = " + ".join(
        f"{p['command']} ({p['wall_seconds'] / 60:.1f} min)" for p in config["parts"]
    )
    out["config"] = config
    out["machine"] = first.get("machine", {})
    return out

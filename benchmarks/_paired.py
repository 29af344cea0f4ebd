"""Paired differences against a reference loss, for the loss and Meta-World reports.

A cell's seed fixes its demonstrations and its held-out starts (``_loss_functions/run.py``),
so two losses at one seed of one task are a pair: the same data and the same episodes,
the loss alone differing. The difference of their scores, pair by pair, is what
``imitrl compare`` measures on episodes; here it is taken per seed (what the reports
keep): mean over the task-seed pairs with a 95% t interval
(:func:`imitrl.evaluation.statistics.t_interval`), which is narrower than comparing two
unpaired intervals wherever tasks and seeds move both losses together.
"""

from __future__ import annotations

from collections.abc import Callable

import _report
from imitrl.evaluation.statistics import t_interval

__all__ = ["paired_differences", "paired_table"]


def paired_differences(
    rows: list[dict],
    reference: Callable[[str], str | None],
    *,
    score: str = "score",
    group: tuple[str, ...] = ("loss", "algorithm"),
) -> list[dict]:
    """``[{"group": (...), "pairs": n, "tasks": k, "diff": (mean, lo, hi), "wins": w,
    "losses": l}]``: per ``group`` (a loss and an algorithm, say), the differences
    ``score - reference score`` over every ``(task, seed)`` where both were measured,
    ``reference(task)`` the task's reference loss (None: no pairs there). ``wins``/``losses``:
    tasks whose mean difference over seeds is above / below 0."""
    by_cell = {(r["task"], r["seed"], *(r[g] for g in group)): r[score] for r in rows}
    out = []
    for key in dict.fromkeys(tuple(r[g] for g in group) for r in rows):
        diffs: dict[str, list[float]] = {}
        for r in rows:
            if tuple(r[g] for g in group) != key:
                continue
            ref = reference(r["task"])
            if ref is None or ref == key[0]:
                continue
            other = by_cell.get((r["task"], r["seed"], ref, *key[1:]))
            if other is not None:
                diffs.setdefault(r["task"], []).append(r[score] - other)
        if not diffs:
            continue
        flat = [d for v in diffs.values() for d in v]
        means = [sum(v) / len(v) for v in diffs.values()]
        out.append({
            "group": key, "pairs": len(flat), "tasks": len(diffs),
            "diff": tuple(float(x) for x in t_interval(flat)),
            "wins": sum(m > 0 for m in means), "losses": sum(m < 0 for m in means),
        })  # fmt: skip
    return out


def paired_table(found: list[dict], names: tuple[str, ...], digits: int = 2) -> str:
    """The differences as a table: ``names`` head the group's columns."""
    header = [*names, "pairs (task x seed)", "mean difference [95% t]", "tasks above / below"]
    body = [[*r["group"], r["pairs"], _report.fmt_ci(r["diff"], digits),
             f"{r['wins']} / {r['losses']} of {r['tasks']}"] for r in found]  # fmt: skip
    return _report.table(header, body)

"""Longest test files first: the order two xdist workers take files in (``--dist
loadfile``, ``--no-loadscope-reorder`` in ``pyproject.toml``).

Each worker takes the next file when it is done with one. xdist's own order (the files
with the most tests first) left a 35-second file of four tests to the end, and one
worker ran alone for the last 40 s of a ten-minute run. ``durations.json`` holds each
file's seconds from a whole run (setup, call and teardown summed); files run longest
first, and a file it does not name (a new one) after them, in collection order. It only
orders: a stale table costs balance, never a test. Refresh it after a file's cost
changes a lot::

    .venv/bin/python -m pytest -q --record-durations
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import pytest

TABLE = Path(__file__).with_name("durations.json")
"""``{test file (from the repository root): seconds}``"""


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--record-durations",
        action="store_true",
        help=f"write each test file's seconds of this run to {TABLE.name} (orders later runs)",
    )


def read_table() -> dict[str, float]:
    """The committed seconds per file; empty when the table is missing or unreadable."""
    try:
        table = json.loads(TABLE.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(table, dict):
        return {}
    return {k: float(v) for k, v in table.items() if isinstance(v, (int, float))}


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Items regrouped by file, the longest files first (stable otherwise)."""
    cost = read_table()
    first: dict[str, int] = {}
    for i, item in enumerate(items):
        first.setdefault(item.nodeid.split("::")[0], i)
    items.sort(key=lambda it: (-cost.get(f := it.nodeid.split("::")[0], 0.0), first[f]))


class _Recorder:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        self.seconds[report.nodeid.split("::")[0]] += report.duration

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        if hasattr(session.config, "workerinput"):  # an xdist worker: the controller writes
            return
        table = {f: round(s, 1) for f, s in sorted(self.seconds.items(), key=lambda x: -x[1])}
        TABLE.write_text(json.dumps(table, indent=1) + "\n")


def pytest_configure(config: pytest.Config) -> None:
    if config.getoption("--record-durations"):
        config.pluginmanager.register(_Recorder(), "imitrl-durations-recorder")

"""The import-time heap frozen out of the collector's walks (``imitrl.system.heap``), and
only by a command that owns its process.

What freezing does is checked in a child process (freezing pytest's own heap would keep
every test's garbage cycles alive); whether the command line freezes is checked
in-process with the freeze replaced by a recorder.
"""

from __future__ import annotations

import gc
import json
import subprocess
import sys
import textwrap

import imitrl.cli as cli

CHILD = textwrap.dedent(
    """
    import gc, json, weakref
    from imitrl.system.heap import freeze_imported

    gc.disable()  # no automatic collection between making a cycle and the freeze

    class Node:
        pass

    def cycle():
        a, b = Node(), Node()
        a.other, b.other = b, a
        return weakref.ref(a)

    before = cycle()  # garbage already at the freeze: frozen with the rest
    frozen = freeze_imported()
    after = cycle()  # garbage made after the freeze: collected as usual
    gc.collect()
    print(json.dumps({
        "frozen": frozen,
        "count": gc.get_freeze_count(),
        "before_alive": before() is not None,
        "after_alive": after() is not None,
    }))
    """
)


def test_freezing_keeps_what_exists_and_collects_what_comes_after():
    # a fresh interpreter: what gc.freeze() keeps is counted from a heap of imports alone
    out = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, check=True, timeout=120
    )
    got = json.loads(out.stdout)
    assert got["frozen"] == got["count"] > 0
    assert got["before_alive"] is True  # a cycle frozen is never freed (the documented cost)
    assert got["after_alive"] is False  # collections go on for what the run creates


TINY = [
    "--env", "CartPole-v1", "--expert", "cartpole", "--demos", "1", "--steps", "5",
    "--batch-size", "16", "--hidden", "16,16", "--eval-episodes", "1",
    "--max-episode-steps", "20",
]  # fmt: skip


def test_the_command_line_freezes_only_a_process_it_owns(monkeypatch, tmp_path):
    events: list[str] = []
    gcs: list[bool] = []  # whether automatic collection is on, at the import and the run
    monkeypatch.setattr(cli, "freeze_imported", lambda: events.append("freeze") or 0)
    load = cli._load

    def logged(spec: str):
        got = load(spec)
        if not spec.endswith(":run_bc"):
            return got
        events.append("imported")
        gcs.append(gc.isenabled())

        def run(config):
            events.append("run")
            gcs.append(gc.isenabled())
            return got(config)

        return run

    monkeypatch.setattr(cli, "_load", logged)
    argv = ["bc", *TINY, "--out", str(tmp_path / "given")]
    assert cli.main(argv) == 0  # a caller's argv: the caller's heap is left alone
    assert events == ["imported", "run"]
    assert gcs == [True, True]  # its collector never paused
    events.clear()
    gcs.clear()
    monkeypatch.setattr(sys, "argv", ["imitrl", "bc", *TINY, "--out", str(tmp_path / "owned")])
    assert cli.main() == 0  # the console script's call: the command owns the process
    assert events == ["imported", "freeze", "run"]  # after its imports, before it runs
    assert gcs == [False, True]  # paused for the imports, back for the run
    assert gc.isenabled()


def test_the_collector_pause_restores_what_it_found_even_on_an_error():
    from imitrl.system.heap import collector_paused

    assert gc.isenabled()
    try:
        with collector_paused():
            assert not gc.isenabled()
            raise ImportError("a missing extra")
    except ImportError:
        pass
    assert gc.isenabled()
    gc.disable()
    try:
        with collector_paused():
            pass
        assert not gc.isenabled()  # it was off: it stays off
    finally:
        gc.enable()

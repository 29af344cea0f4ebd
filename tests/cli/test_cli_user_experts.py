"""The README's continuous-control table, on a tiny budget: `imitrl dagger` on an env no
built-in expert covers, with the user-written expert module in examples/mypkg."""

from __future__ import annotations

import json

from imitrl.cli import main


def test_dagger_from_the_cli_with_a_user_expert_on_mountain_car(mypkg, tmp_path, capsys):
    argv = [
        "dagger", "--env", "MountainCarContinuous-v0",
        "--expert", "mypkg.experts:mountain_car", "--expert-kind", "callable",
        "--demos", "1", "--rounds", "2", "--episodes-per-round", "1", "--steps", "300",
        "--batch-size", "128", "--eval-episodes", "4", "--no-progress", "--out", str(tmp_path),
    ]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    results = json.loads((tmp_path / "results.json").read_text())
    # the bang-bang expert reaches the flag (return ~92); its labels sit on the bounds
    assert results["expert"]["mean_return"] > 85.0
    assert len(results["rounds"]) == 2
    assert (tmp_path / "curves.png").stat().st_size > 0

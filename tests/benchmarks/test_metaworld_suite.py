"""benchmarks/_metaworld_suite.py (metaworld_mt10.py, metaworld_mt50.py) --merge: cells of runs apart, one report, refusals."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

pytest.importorskip("metaworld")
from _metaworld_suite import merge  # noqa: E402

PROTOCOL = {"demo_episodes": 5, "rounds": 3}


def _run(loss: str, seeds: list[int], *, expert: float = 1.0, demos=(5,)) -> dict:
    tasks = [f"reach-v3/{n}demo" for n in demos]
    return {
        "config": {"tasks": ["reach-v3"], "losses": [loss], "demos": list(demos),
                   "seeds": len(seeds), "jobs": 2, "protocol": {t: PROTOCOL for t in tasks}},
        "rows": [{"task": t, "loss": loss, "seed": s, "algorithm": a, "score": 0.5}
                 for t in tasks for s in seeds for a in ("bc", "dagger")],
        "references": [{"task": t, "policy": "expert", "seed": s, "score": expert}
                       for t in tasks for s in seeds],
        "wall_seconds": 60.0,
        "load_average_start": [1.0], "load_average_end": [2.0],
    }  # fmt: skip


def test_merge_joins_disjoint_cells_and_keeps_only_the_asked_demonstrations():
    full = _run("mse", [0, 1], demos=(1, 5))
    merged = merge([full, _run("diffusion_unet", [0]), _run("diffusion_unet", [1])], (5,))
    assert merged["config"]["losses"] == ["mse", "diffusion_unet"]
    assert merged["config"]["seeds"] == 2 and merged["config"]["jobs"] == "merged"
    assert {r["task"] for r in merged["rows"]} == {"reach-v3/5demo"}
    assert len(merged["rows"]) == 2 * 2 * 2  # losses x seeds x algorithms
    assert len(merged["references"]) == 2  # one per seed, shared by the runs
    assert merged["wall_seconds"] == 180.0


def test_merge_refuses_disagreements():
    with pytest.raises(ValueError, match=r"another .* reference"):
        merge([_run("mse", [0]), _run("act", [0], expert=0.8)], (5,))
    with pytest.raises(ValueError, match="repeats the cell"):
        merge([_run("mse", [0]), _run("mse", [0])], (5,))
    with pytest.raises(ValueError, match=r"diffusion_unet has seeds \[0\]"):
        merge([_run("mse", [0, 1]), _run("diffusion_unet", [0])], (5,))
    other = _run("act", [0])
    other["config"]["protocol"] = {"reach-v3/5demo": {**PROTOCOL, "rounds": 4}}
    with pytest.raises(ValueError, match="another protocol"):
        merge([_run("mse", [0]), other], (5,))
    with pytest.raises(ValueError, match="at least two"):
        merge([_run("mse", [0])], (5,))


@pytest.mark.parametrize(
    "argv, said",
    [(["--seeds", "0"], "--seeds must be >= 1, got 0"),
     (["--jobs", "0"], "--jobs must be >= 1, got 0"),
     (["--first-seed", "-1"], "--first-seed must be >= 0, got -1"),
     (["--demos", "5", "0"], "--demos must be >= 1, got 0"),
     (["--demos", "5", "5"], "--demos repeats a count: [5, 5]"),
     (["--losses", "nope"], "--losses: ['nope'] are not registered losses"),
     (["--first-seed", str(2**70)], f"--first-seed {2**70} + --seeds")],
)  # fmt: skip
def test_bad_counts_are_one_line_before_anything_runs(argv, said, capsys):
    from metaworld_mt50 import main

    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2 and said in capsys.readouterr().err


def test_a_beta_decay_outside_0_1_is_refused():
    from dataclasses import replace

    from metaworld_mt50 import PROTOCOL

    with pytest.raises(ValueError, match=r"beta_decay must be in \[0, 1\] or None, got 1.5"):
        replace(PROTOCOL, beta_decay=1.5)


def test_a_merge_with_a_demonstration_count_missing_is_refused():
    """A hostile review: a part with mse at 1 and 5 demos and one with the other losses at 1
    merged, and the report said "0 tasks" for cells that did not exist."""
    with pytest.raises(ValueError, match=r"act has no cells on \['reach-v3/5demo'\]"):
        merge([_run("mse", [0], demos=(1, 5)), _run("act", [0], demos=(1,))], (1, 5))


def test_a_render_or_merge_of_a_file_that_is_not_the_suites_is_one_line(tmp_path, capsys):
    """A hostile review: MT50's script rendered MT10's file under MT50's name; bad files
    were tracebacks; a --quick render rewrote the committed block, JSON and figure."""
    from metaworld_mt10 import main as mt10
    from metaworld_mt50 import main as mt50

    committed = ROOT / "benchmarks" / "results"
    watched = [ROOT / "benchmarks" / "README.md", *committed.glob("metaworld_mt*")]
    before = {p: p.read_bytes() for p in watched}
    bad = tmp_path / "bad.json"
    for text, said in (("{", "not a results file (JSONDecodeError"),
                       ('{"config": {"suite": "MT10"}, "rows": NaN}', "NaN is not a finite"),
                       ("[1]", "a JSON list, not an object"),
                       ('{"config": {"suite": "MT10"}}', "not a results file this report reads")):  # fmt: skip
        bad.write_text(text)
        with pytest.raises(SystemExit) as stop:
            mt10(["--render", str(bad)])
        assert stop.value.code == 2 and said in capsys.readouterr().err
    with pytest.raises(SystemExit):
        mt50(["--render", str(committed / "metaworld_mt10.json"), "--out", str(tmp_path / "x")])
    assert "a results file of MT10, not MT50" in capsys.readouterr().err
    mt10(["--quick", "--render", str(committed / "metaworld_mt10.json")])
    assert "--quick without --out: writing to" in capsys.readouterr().out
    assert {p: p.read_bytes() for p in watched} == before  # nothing committed rewritten

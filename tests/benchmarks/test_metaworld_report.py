"""benchmarks/_metaworld_report.py: the suite's target, the tasks short of it, and the
paired table of a one-loss run (DAgger and BC against BC at DAgger's queries), and of
several losses (each against mse, and each loss's DAgger against its BC at DAgger's queries)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

pytest.importorskip("metaworld")
from _metaworld_report import markdown  # noqa: E402

PROTOCOL = {"demo_episodes": 10, "rounds": 3, "episodes_per_round": 3, "round_steps": 160,
            "bc": {"num_steps": 320, "batch_size": 256}, "learner": {"hidden": [128, 128], "lr": 3e-3},
            "eval_episodes": 5, "max_episode_steps": None, "beta_decay": 0.5}  # fmt: skip


def _payload(suite: str | None, tasks: list[str], dagger: dict[str, int]) -> dict:
    """One loss (mse), 10 demonstrations, 2 seeds of 5 episodes; the expert 5/5 a seed;
    DAgger ``dagger[task]`` successes a seed, BC 2 and BC at DAgger's queries 4."""
    rows = []
    for t in tasks:
        for seed in (0, 1):
            for algorithm, k in (("bc", 2), ("dagger", dagger[t]), ("bc_matched", 4)):
                rows.append({"task": f"{t}/10demo", "loss": "mse", "seed": seed,
                             "algorithm": algorithm, "successes": k, "episodes": 5,
                             "score": k / 5, "rows_trained": 900})  # fmt: skip
    config = {"tasks": tasks, "losses": ["mse"], "demos": [10], "seeds": 2, "jobs": 2,
              "protocol": {f"{t}/10demo": PROTOCOL for t in tasks}}  # fmt: skip
    if suite is not None:
        config["suite"] = suite
    refs = [{"task": f"{t}/10demo", "policy": "expert", "seed": s, "successes": 5, "episodes": 5,
             "score": 1.0} for t in tasks for s in (0, 1)]  # fmt: skip
    return {"config": config, "rows": rows, "references": refs, "wall_seconds": 60.0,
            "load_average_start": [1.0], "load_average_end": [1.0]}  # fmt: skip


def test_mt50s_target_and_the_tasks_short_of_it_are_named():
    text = markdown(
        _payload("MT50", ["reach-v3", "push-v3"], {"reach-v3": 5, "push-v3": 4}), "f.png"
    )
    assert ">= 45 of 50 tasks from <= 10 demonstrations): not met" in text
    assert "mse 10 demo(s): 1." in text
    assert (
        "Short of it (mse, 10 demonstrations), 1 tasks; BC at DAgger's queries is short too, 1: "
        "push-v3 (DAgger 8/10, BC at its queries 8/10, the expert 10/10)." in text
    )
    assert "at most 500 steps (Meta-World's own limit)" in text
    assert "beta p^(i-1) = 0.5^(i-1) in round i (Ross et al.)" in text
    assert "![Meta-World MT50](f.png)" in text


def test_a_payload_without_a_suite_is_mt10s():
    text = markdown(_payload(None, ["reach-v3"], {"reach-v3": 5}), "f.png")
    assert ">= 8 of 10 tasks from <= 5 demonstrations)" in text and "Short of it" not in text


def test_one_loss_pairs_its_algorithms_against_bc_at_daggers_queries():
    text = markdown(
        _payload("MT50", ["reach-v3", "push-v3"], {"reach-v3": 5, "push-v3": 4}), "f.png"
    )
    assert "Paired differences against BC at DAgger's queries" in text
    # DAgger - BC at its queries: reach +0.2, push 0.0 on both seeds; BC - it: -0.4 everywhere
    assert "| DAgger | 10 | 4 | 0.10 [" in text and "| 1 / 0 of 2 |" in text
    assert "| BC | 10 | 4 | -0.40 [-0.40, -0.40] | 0 / 2 of 2 |" in text


def test_the_tasks_short_of_it_are_grouped_by_how_far():
    """push: DAgger 9/10, one success short of 0.95 x the expert's 10/10; pick-place:
    DAgger 4/10 where BC at its queries reaches 10/10; the default rows: BC at its queries
    8/10, short too (door-open)."""
    payload = _payload(
        "MT50", ["reach-v3", "push-v3", "pick-place-v3", "door-open-v3"],
        {"reach-v3": 5, "push-v3": 4, "pick-place-v3": 2, "door-open-v3": 3},
    )  # fmt: skip
    for r in payload["rows"]:
        if (r["task"], r["algorithm"], r["seed"]) == ("push-v3/10demo", "dagger", 0):
            r["successes"] = 5
        if (r["task"], r["algorithm"]) == ("pick-place-v3/10demo", "bc_matched"):
            r["successes"] = 5
    text = markdown(payload, "f.png")
    assert (
        "Short of it (mse, 10 demonstrations), 3 tasks; one more success would reach it, 1: "
        "push-v3 (DAgger 9/10, BC at its queries 8/10, the expert 10/10); BC at DAgger's "
        "queries reaches it (the same number of expert labels, all from the expert's own "
        "episodes), 1: pick-place-v3 (DAgger 4/10, BC at its queries 10/10, the expert 10/10); "
        "BC at DAgger's queries is short too, 1: door-open-v3 (DAgger 6/10, BC at its queries "
        "8/10, the expert 10/10)."
    ) in text


def test_several_losses_each_pair_dagger_against_bc_at_its_queries():
    """Two losses: mse's DAgger 5/5 a seed and act's 3/5 (a copy of mse's rows), BC at
    DAgger's queries 4/5 for both: +0.2 and -0.2 on every task and seed."""
    payload = _payload(None, ["reach-v3", "push-v3"], {"reach-v3": 5, "push-v3": 5})
    act = [{**r, "loss": "act"} for r in payload["rows"]]
    for r in act:
        if r["algorithm"] == "dagger":
            r["successes"], r["score"] = 3, 0.6
    payload["rows"] += act
    payload["config"]["losses"] = ["mse", "act"]
    text = markdown(payload, "f.png")
    assert (
        "DAgger against BC at DAgger's queries (the same number of expert labels), per loss" in text
    )
    assert "| mse | 10 | DAgger | 4 | 0.20 [0.20, 0.20] | 2 / 0 of 2 |" in text
    assert "| act | 10 | DAgger | 4 | -0.20 [-0.20, -0.20] | 0 / 2 of 2 |" in text

"""The GAIL peer harness: each protocol's settings, and every ratio labelled with its protocol."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _peer_imitation.gail_report import markdown, summarise  # noqa: E402
from _peer_imitation.gail_tasks import (  # noqa: E402
    IMITATION,
    IMITATION_AIRL,
    IMITRL,
    IMITRL_AIRL,
    TASKS,
    settings,
)


def test_own_gives_each_library_its_settings_and_matched_gives_imitrl_imitations():
    cart = TASKS["cartpole"]
    assert settings(cart, "imitation", "own") == IMITATION == settings(cart, "imitation", "matched")
    assert settings(cart, "imitrl", "own") == IMITRL
    matched = settings(cart, "imitrl", "matched")
    assert {k: matched[k] for k in IMITRL} == {k: IMITATION[k] for k in IMITRL}
    # a task's lr and gamma bind both libraries under both protocols
    pend = TASKS["pendulum"]
    for library in ("imitrl", "imitation"):
        for protocol in ("own", "matched"):
            s = settings(pend, library, protocol)
            assert (s["lr"], s["gamma"]) == (1e-3, 0.9)
    with pytest.raises(ValueError, match="protocol must be one of"):
        settings(cart, "imitrl", "beta0")
    # equal env steps: whole rounds on both sides, n_steps = rollout_steps / lanes
    for task in TASKS.values():
        assert task.total_steps % task.rollout_steps == 0 and task.rollout_steps % task.lanes == 0


def test_airl_rows_take_imitations_airl_tutorial_and_imitrls_airl_defaults():
    cart, pend = TASKS["cartpole_airl"], TASKS["pendulum_airl"]
    assert cart.method == pend.method == "airl" and TASKS["cartpole"].method == "gail"
    assert settings(cart, "imitation", "own") == IMITATION_AIRL
    assert settings(cart, "imitation", "matched") == IMITATION_AIRL
    assert settings(cart, "imitrl", "own") == IMITRL_AIRL
    assert (IMITATION_AIRL["clip_epsilon"], IMITATION_AIRL["discriminator_updates"]) == (0.1, 16)
    matched = settings(cart, "imitrl", "matched")  # imitation's numbers, imitrl's own w
    assert {k: matched[k] for k in IMITATION_AIRL} == IMITATION_AIRL
    assert matched["entropy_weight"] == IMITRL_AIRL["entropy_weight"] == 1.0
    # Pendulum: the task's lr, gamma and imitrl's recommended w = 0 under both protocols
    for protocol in ("own", "matched"):
        s = settings(pend, "imitrl", protocol)
        assert (s["lr"], s["gamma"], s["entropy_weight"]) == (1e-3, 0.9, 0.0)
        assert "entropy_weight" not in settings(pend, "imitation", protocol)
    # imitation's demonstration batch fits in the demonstrations' transitions
    assert pend.demo_episodes * 200 >= IMITATION_AIRL["discriminator_batch"]


def _run(library, protocol, seed, wall, ret):
    phases = {"imports": 1.0, "setup": 0.5, "train": wall - 2.0, "evaluation": 0.5,
              "in_process": wall - (0.25 if library == "imitrl" else 1.25)}  # fmt: skip
    return {"task": "cartpole", "library": library, "protocol": protocol, "seed": seed,
            "wall": wall, "phases": phases, "returns": {"final": ret}}  # fmt: skip


def test_every_ratio_is_labelled_with_its_protocol_and_judged_per_seed():
    runs = [
        _run("imitrl", "own", 0, 8.0, 500.0), _run("imitation", None, 0, 20.0, 480.0),
        _run("imitrl", "matched", 0, 12.0, 470.0),
        _run("imitrl", "own", 1, 9.0, 500.0), _run("imitation", None, 1, 20.0, 500.0),
        _run("imitrl", "matched", 1, 11.0, 500.0),
    ]  # fmt: skip
    summary = summarise(runs)["cartpole"]
    assert set(summary) == {"own", "matched"}
    assert summary["own"]["phases"]["wall"]["ratios"] == [0.4, 0.45]
    assert summary["own"]["wall_met"] is True and summary["own"]["returns_met"] is True
    assert summary["matched"]["phases"]["wall"]["ratios"] == [0.6, 0.55]
    assert summary["matched"]["wall_met"] is False
    assert summary["matched"]["returns_met"] is False  # 470 < 480 on seed 0
    raw = {"config": {"seeds": 2}, "imitrl_versions": {}, "peer_versions": None,
           "summary": summarise(runs), "wall_seconds": 1.0}  # fmt: skip
    lines = [line for line in markdown(raw).splitlines() if line.startswith("| cartpole")]
    assert [line.split("|")[2].strip() for line in lines] == ["own", "matched"]
    assert "0.40 / 0.45" in lines[0] and "**no**" in lines[1]
    # the process outside the child's clock (start and exit), each side's own
    assert summary["own"]["phases"]["outside"]["imitrl"] == [0.25, 0.25]
    assert summary["own"]["phases"]["outside"]["imitation"] == [1.25, 1.25]
    assert "| 0.2 / 0.2 | 1.2 / 1.2 |" in lines[0]
    # the median and every seed, each judged in its own column
    uneven = [_run("imitrl", "own", s, w, 500.0) for s, w in enumerate((8.0, 9.0, 11.0))]
    uneven += [_run("imitation", None, s, 20.0, 480.0) for s in range(3)]
    own = summarise(uneven)["cartpole"]["own"]
    assert own["wall_met"] is True and own["wall_met_each_seed"] is False  # 0.55 on seed 2
    assert summary["own"]["wall_met_each_seed"] is True
    raw = {"config": {"seeds": 3, "bytecode": "imitrl's modules byte-compiled"},
           "imitrl_versions": {}, "peer_versions": None, "summary": summarise(uneven),
           "wall_seconds": 1.0}  # fmt: skip
    text = markdown(raw)
    assert "Bytecode: imitrl's modules byte-compiled." in text
    (line,) = [x for x in text.splitlines() if x.startswith("| cartpole | own")]
    assert line.split("|")[-4:-1] == [" yes ", " **no** ", " yes "]

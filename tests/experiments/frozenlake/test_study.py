"""`imitrl frozenlake`: the section's numbers to the digit, exact values beside them, figures."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from imitrl.cli import main
from imitrl.tabular import (
    TabularMDP,
    greedy,
    linear_reward,
    next_state_features,
    soft_value_iteration,
    success_probability,
    value_iteration,
)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("frozenlake")
    assert main(["frozenlake", "--out", str(out), "--no-progress"]) == 0
    return out, json.loads((out / "results.json").read_text())


def test_demonstrations_and_fit(study):
    _, r = study
    assert r["protocol"] == "faithful"
    assert r["expert"]["policy"] == [0, 3, 0, 3, 0, 0, 0, 0, 3, 1, 0, 0, 0, 2, 1, 0]
    assert f"{r['expert']['V_start']:.6f}" == "0.180472"
    assert (r["demos"]["pairs"], r["demos"]["states_covered"], r["demos"]["reachable_states"]) == (
        96,
        7,
        11,
    )
    assert r["demos"]["uncovered"] == [1, 2, 3, 13]
    assert f"{r['bc']['cross_entropy']:.3f}" == "0.004"
    assert (
        str(np.round(np.array(r["bc"]["probs"]["9"], dtype=np.float32), 3))
        == "[0.001 0.996 0.001 0.001]"
    )
    assert (
        str(np.round(np.array(r["bc"]["probs"]["3"], dtype=np.float32), 3))
        == "[0.25 0.25 0.25 0.25]"
    )
    assert r["bc"]["mistakes"] == 0


def test_success_rates_with_exact_values(study):
    _, r = study
    ev = r["evaluation"]
    assert f"{ev['expert']['rate']:.1%}" == "73.4%" and f"{ev['clone']['rate']:.1%}" == "17.5%"
    assert ev["expert"]["episodes"] == 1000
    assert f"{ev['expert']['exact']:.6f}" == "0.729766"
    # every estimate's exact value lies in its interval, and the clone's exact value is priced too
    for name in ("expert", "clone"):
        assert ev[name]["ci"][0] <= ev[name]["exact"] <= ev[name]["ci"][1]
    assert f"{ev['clone']['exact']:.2%}" == "18.97%"


def test_sweep(study):
    _, r = study
    got = [
        (f"{r['sweep'][n]['median']:.0%}", f"{r['sweep'][n]['worst']:.0%}")
        for n in ("1", "3", "10")
    ]
    assert got == [("44%", "0%"), ("73%", "70%"), ("73%", "70%")]
    assert all(len(r["sweep"][n]["exact"]) == 10 for n in ("1", "3", "10"))


def test_chain(study):
    _, r = study
    a, b = r["chain"]["panels"]
    assert (a["eps"], a["T"], b["eps"], b["T"]) == (0.05, 10, 0.01, 64)
    assert f"{a['cloned'][-1]:.2f}" == "2.40" and f"{a['recovering'][-1]:.2f}" == "0.51"
    assert a["cloned_exact"][-1] == pytest.approx(
        10 - sum(0.95**t for t in range(1, 11)), abs=1e-12
    )
    assert b["ratio_exact"] == pytest.approx(
        (64 - sum(0.99**t for t in range(1, 65))) / 0.64, abs=1e-9
    )


def test_divergence(study):
    _, r = study
    tv = r["divergence"]["tv"]
    assert [f"{tv[t]:.3f}" for t in ("3", "5", "10", "20")] == ["0.000", "0.004", "0.063", "0.227"]
    hole = r["divergence"]["hole_mass"]["12"]
    assert (f"{hole['expert']:.3f}", f"{hole['clone']:.3f}") == ("0.000", "0.221")
    assert r["divergence"]["worst_hole"] == 12


def test_dagger(study):
    _, r = study
    rounds = r["dagger"]["rounds"]
    assert [x["pairs"] for x in rounds] == [96, 188, 273, 426]
    assert [f"{x['rate']:.1%}" for x in rounds] == ["18.0%", "72.0%", "72.2%", "71.9%"]
    # the exact success of each round's policy (round 0 is the section's clone)
    assert [f"{x['exact']:.2%}" for x in rounds] == ["18.97%", "71.10%", "71.10%", "72.98%"]
    assert rounds[-1]["exact"] == pytest.approx(r["expert"]["exact_success"], abs=1e-12)


def test_exercises_and_prose_checks(study):
    out, r = study
    ex = r["exercises"]
    # Exercise 2's answer quotes its table's row (issue 44: "losing 0.0000" in the table,
    # "lose 1.13%" in the answer, two thresholds)
    text = (out / "report.txt").read_text()
    answer = re.search(r"answer: at N = (\d+) clones .*? yet lose ([\d.]+%) success", text)
    assert answer is not None, "Exercise 2 has no answer line"
    row = re.search(rf"^\s*{answer[1]} \|.*, losing ([\d.]+%) success", text, re.M)
    assert row is not None and row[1] == answer[2]
    assert set(ex["demo_counts"]) >= {"5", "20", "100", "500"}
    assert len(ex["state_errors"]["error"]) == 11
    assert len(ex["budget"]["dagger"]) == 10 and len(ex["corruption"]["bc_corrupted"]) == 10
    claims = {c["claim"]: c for c in r["prose_checks"]}
    thirty = next(c for k, c in claims.items() if "thirtyfold" in k)
    assert not thirty["agrees"] and thirty["exact"] == pytest.approx(26.6, abs=0.05)
    five = next(c for k, c in claims.items() if "five times" in k)
    assert five["agrees"] and five["exact"] == pytest.approx(2.3756 / 0.5, abs=1e-3)
    one_round = next(c for k, c in claims.items() if "one DAgger round" in k)
    assert not one_round["agrees"] and f"{one_round['exact']:.4f}" == "0.7110"
    assert all(c["agrees"] for k, c in claims.items() if "success rate" in k)


def test_report_and_figures(study):
    out, _ = study
    text = (out / "report.txt").read_text()
    for line in (
        "96 state-action pairs from 3 expert episodes, covering 7 of 11 reachable states",
        "success rate: expert 73.4%, clone 17.5%",
        "round 3: trained on 426 pairs, success rate 71.9%",
        "vs exact 72.98%",
    ):
        assert line in text
    for name in (
        "chain",
        "occupancy",
        "sweep",
        "dagger",
        "ex_demo_counts",
        "ex_state_errors",
        "ex_budget",
        "ex_corruption",
        "irl_reward",
        "irl_sweep",
        "airl_transfer",
    ):
        png = out / f"{name}.png"
        head = png.read_bytes()[:24]
        assert head[:8] == b"\x89PNG\r\n\x1a\n"
        width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        assert width >= 400 and height >= 300 and png.stat().st_size > 10_000


def test_irl_section(study):
    """Section 8: exact values, recomputed here from the printed policy and reward."""
    out, r = study
    text = (out / "report.txt").read_text()
    fit = r["irl"]["fit"]
    assert (
        "planning against it: greedy policy 72.98% exact success, soft-optimal policy "
        f"{fit['exact_success_soft']:.2%} (the expert 72.98%, the clone 18.97%)"
    ) in text
    assert (
        "on the 4 reachable states the demonstrations never visited [1, 2, 3, 13]: "
        "IRL's greedy action is the expert's on 4, the clone's on 1"
    ) in text
    mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95)
    policy = torch.tensor(fit["policy"])
    assert success_probability(mdp, policy) == pytest.approx(fit["exact_success_greedy"], abs=1e-12)
    # the greedy plan is the argmax of the soft Q_0 of the printed reward
    reward = linear_reward(
        torch.tensor(fit["theta"], dtype=torch.float64), next_state_features(mdp)
    )
    q0 = soft_value_iteration(mdp, reward).q[0]
    live = ~mdp.terminal
    assert torch.equal(q0.argmax(-1)[live], policy[live])
    assert fit["demonstrations_argmax"] == 1.0 and fit["log_likelihood"] > -1.0
    for n in ("1", "3", "10"):
        assert {len(v) for v in r["irl"]["sweep"][n].values()} == {10}
    assert r["irl"]["sweep"]["10"]["irl"][0] == pytest.approx(fit["exact_success_greedy"])
    targets = {t["target"]: t for t in r["irl"]["transfer"]}
    assert set(targets) == {"is_slippery=False", "success_rate=0.5", "success_rate=0.9"}
    det = TabularMDP.from_gym("FrozenLake-v1", 0.95, make_kwargs={"is_slippery": False})
    own = greedy(det.backup(value_iteration(det, 1000)[-1]))
    assert targets["is_slippery=False"]["target_expert"] == success_probability(det, own) == 1.0
    claims = {c["claim"]: c for c in r["prose_checks"]}
    assert claims["planning against the inferred reward recovers the expert"]["agrees"]


def test_airl_section(study):
    """Section 8b: the reported scores recompute from the printed rewards; with unlimited
    demonstrations AIRL's g is every kernel's own optimum, the source-shaped f is not."""
    from imitrl.tabular import airl as A
    from imitrl.tabular.dp import policy_evaluation

    out, r = study
    text = (out / "report.txt").read_text()
    assert "8b. Beyond cloning: AIRL's reward under changed dynamics, exactly" in text
    section = r["airl"]
    assert section["beta"] == 20.0 and 0.2 < section["demonstrator_success"] < 0.3
    fits = {f["dataset"]: f for f in section["fits"]}
    assert list(fits) == ["10 episodes", "100 episodes", "1000 episodes", "unlimited"]
    kernels = {
        "source": {},
        "is_slippery=False": {"is_slippery": False},
        "success_rate=0.5": {"success_rate": 0.5},
        "success_rate=0.9": {"success_rate": 0.9},
    }
    rows = {(row["target"], row["dataset"]): row for row in section["transfer"]}
    assert {t for t, _ in rows} == set(kernels)
    for name, kwargs in kernels.items():
        mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95, make_kwargs=kwargs)
        own = greedy(mdp.backup(value_iteration(mdp, 1000)[-1]))
        uniform = torch.full((16, 4), 0.25, dtype=torch.float64)
        v_own, v_uni = (float(mdp.initial @ policy_evaluation(mdp, p)) for p in (own, uniform))
        for dataset, fit in fits.items():
            g = torch.tensor(fit["g"], dtype=torch.float64)
            plan = A.plan(mdp, g)
            v = float(mdp.initial @ policy_evaluation(mdp, plan))
            row = rows[(name, dataset)]
            assert row["airl_g"]["normalised_return"] == pytest.approx(
                (v - v_uni) / (v_own - v_uni), abs=1e-9
            )
            assert row["airl_g"]["success"] == pytest.approx(success_probability(mdp, plan))
        assert rows[(name, "unlimited")]["airl_g"]["normalised_return"] == pytest.approx(1.0)
    assert rows[("is_slippery=False", "unlimited")]["airl_f"]["normalised_return"] < 0.5
    assert rows[("is_slippery=False", "unlimited")]["maxent"]["normalised_return"] < 0.5


def _small(out, *extra):
    return [
        "frozenlake",
        "--out",
        str(out),
        "--no-progress",
        "--no-exercises",
        "--eval-episodes",
        "200",
        "--sweep-datasets",
        "3",
        "--sweep-eval-episodes",
        "50",
        "--chain-samples",
        "2000",
        "--irl-steps",
        "10",
        "--irl-datasets",
        "2",
        "--irl-sizes",
        "1",
        *extra,
    ]


def test_same_seed_same_digits(tmp_path):
    runs = []
    for i in range(2):
        assert main(_small(tmp_path / str(i))) == 0
        r = json.loads((tmp_path / str(i) / "results.json").read_text())
        r.pop("timing")
        r["config"].pop("out")
        runs.append(r)
    assert runs[0] == runs[1]


@pytest.mark.parametrize(
    "extra",
    [
        ("--map-name", "8x8", "--probe-states", "9,63"),
        ("--desc", "SFFH,FHFF,FFFF,HFFG", "--protocol", "batched", "--eval-scale", "5"),
    ],
)
def test_other_maps_and_protocols(tmp_path, extra):
    assert main(_small(tmp_path, *extra)) == 0
    r = json.loads((tmp_path / "results.json").read_text())
    assert 0 < r["expert"]["exact_success"] <= 1
    assert (
        r["evaluation"]["expert"]["ci"][0]
        <= r["evaluation"]["expert"]["exact"]
        <= r["evaluation"]["expert"]["ci"][1]
    )


@pytest.mark.parametrize(
    "extra, probe",
    [
        (("--no-slippery",), None),  # the expert never fails: ratios of failures are undefined
        (("--env-id", "CliffWalking-v1", "--max-steps", "60"), (0, 36)),
        (
            ("--env-id", "Taxi-v4", "--dagger-rounds", "2", "--no-irl"),
            (0, 1),
        ),  # no grid: state-index plot
    ],
)
def test_other_toy_text_envs(tmp_path, extra, probe):
    flags = [*extra] + ([] if probe is None else ["--probe-states", ",".join(map(str, probe))])
    assert main(_small(tmp_path, *flags)) == 0
    r = json.loads((tmp_path / "results.json").read_text())
    mdp = TabularMDP.from_gym(
        r["config"]["env_id"],
        0.95,
        make_kwargs={} if r["config"]["slippery"] is None else {"is_slippery": False},
        max_steps=r["config"]["max_steps"],
    )
    V = value_iteration(mdp, 1000)[-1]
    expert = greedy(mdp.backup(V))
    assert r["expert"]["exact_success"] == pytest.approx(
        float(success_probability(mdp, expert, mdp.max_steps)), abs=1e-12
    )
    assert (tmp_path / "occupancy.png").stat().st_size > 0
    report = (tmp_path / "report.txt").read_text()
    stochastic = "stochastic" if bool((mdp.P.amax(-1) < 1).any()) else "deterministic"
    assert f"{mdp.name}, {stochastic} transitions, time limit {mdp.max_steps}" in report
    if r["evaluation"]["expert"]["exact"] == 1.0:
        assert "undefined, the expert never fails" in report


def test_bad_flags_fail_clearly(tmp_path, capsys):
    assert main(["frozenlake", "--out", str(tmp_path), "--env-id", "NoSuchLake-v0"]) == 2
    assert "unknown or unbuildable gymnasium env id 'NoSuchLake-v0'" in capsys.readouterr().err
    assert main(["frozenlake", "--out", str(tmp_path), "--env-id", "CartPole-v1"]) == 2
    assert "env 'CartPole-v1' has no tabular model" in capsys.readouterr().err
    assert main(["frozenlake", "--out", str(tmp_path), "--env-id", "Taxi-v4", "--slippery"]) == 2
    assert "'Taxi-v4' rejected the arguments {'is_slippery': True}" in capsys.readouterr().err
    assert main(["frozenlake", "--out", str(tmp_path), "--env-id", "CliffWalking-v1"]) == 2
    assert "'CliffWalking-v1' is registered without a time limit" in capsys.readouterr().err
    assert main(["frozenlake", "--out", str(tmp_path), "--desc", "SFF,FHF,FFG"]) == 2
    assert "--probe-states [9] outside the 9 states" in capsys.readouterr().err
    taxi = ["--env-id", "Taxi-v4", "--protocol", "batched", "--probe-states", "0"]
    assert main(["frozenlake", "--out", str(tmp_path), *taxi]) == 2
    assert "pins each lane to one start state, and 'Taxi-v4' has 300" in capsys.readouterr().err
    assert main(["frozenlake", "--out", str(tmp_path), "--protocol", "gpu"]) == 2
    bad = ["--irl-transfer", "no_such_argument:1"]
    assert main(["frozenlake", "--out", str(tmp_path), *bad]) == 2
    err = capsys.readouterr().err
    assert "--irl-transfer no_such_argument:1: FrozenLake-v1 cannot be built" in err
    assert not any(tmp_path.iterdir())  # refused before any work or output


def test_console_entry_points(tmp_path):
    script = Path(sys.executable).parent / "imitrl"  # the installed console script
    for exe in ([str(script)], [sys.executable, "-m", "imitrl"]):
        out = subprocess.run(
            [*exe, "frozenlake", "--help"], capture_output=True, text=True, check=True
        )
        assert "--protocol" in out.stdout and "--ex-corruption" in out.stdout


def test_malformed_flag_values_are_usage_errors(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["frozenlake", "--chain-panels", "0.05"])
    assert exit_info.value.code == 2
    assert "expected comma-separated a:b pairs" in capsys.readouterr().err

"""The study's prose checks read the number their claim is about (a review at other
settings: ``--tv-steps ...,40`` checked "22 percent by step 20" against step 40's mass;
tied soft-optimal actions counted as not the most likely; a chain panel without a
sampled recovering loss printed ``nanx`` and numpy warnings)."""

from __future__ import annotations

import json
import warnings

import pytest

from imitrl.cli import main
from tests.experiments.frozenlake.test_study import _small


def _run(out, *extra) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # numpy's divide warnings too
        assert main(_small(out, "--no-airl", *extra)) == 0
    return json.loads((out / "results.json").read_text())


def _claim(results: dict, start: str) -> dict | None:
    found = [c for c in results["prose_checks"] if c["claim"].startswith(start)]
    return found[0] if found else None


@pytest.mark.parametrize("steps", ["3,5,10,20,40", "20,60"])
def test_the_hole_claim_reads_step_20_whatever_the_largest_step(tmp_path, steps):
    results = _run(tmp_path / "out", "--tv-steps", steps)
    claim = _claim(results, "the clone parks 22 percent of its mass in hole")
    assert claim is not None and claim["agrees"], claim
    at = results["divergence"]["hole_mass_at_20"]
    hole = results["divergence"]["worst_hole_at_20"]
    assert claim["measured"] == at[str(hole)]["clone"]
    # 0.220865: the clone's mass in hole 12 after 20 steps, by a numpy walk of gymnasium's
    # own transition table (an independent check of the seed's clone)
    assert claim["measured"] == pytest.approx(0.220865, abs=1e-6)


def test_the_hole_claim_is_not_checked_before_step_20(tmp_path):
    results = _run(tmp_path / "out", "--tv-steps", "3,5,10")
    assert _claim(results, "the clone parks 22 percent") is None
    assert "hole_mass_at_20" not in results["divergence"]


def test_tied_most_likely_actions_count_as_most_likely(tmp_path):
    """On ``GS`` the start's three non-goal actions tie under the soft-optimal policy."""
    results = _run(tmp_path / "out", "--desc", "GS", "--probe-states", "1")
    claim = _claim(results, "maximum-entropy IRL infers a reward")
    assert claim is not None and claim["measured"] == 1.0 and claim["agrees"], claim


def test_a_chain_panel_without_a_recovering_loss_has_no_ratio(tmp_path):
    results = _run(tmp_path / "out", "--chain-panels", "0.001:1,0.5:3", "--chain-samples", "5")
    first, second = results["chain"]["panels"]
    assert first["ratio"] is None and first["ratio_exact"] == pytest.approx(1.0)
    assert second["ratio"] == pytest.approx(second["cloned"][-1] / second["recovering"][-1])
    report = (tmp_path / "out" / "report.txt").read_text()
    assert "ratio measured undefined (no recovering loss sampled)" in report
    assert "nan" not in report


def test_the_batched_protocol_checks_no_claim_about_its_own_draw(tmp_path):
    """IRL fits section 1's demonstrations, which the batched protocol draws otherwise."""
    results = _run(tmp_path / "out", "--protocol", "batched", "--eval-scale", "1")
    assert _claim(results, "maximum-entropy IRL infers a reward") is None
    assert _claim(results, "planning against the inferred reward") is None
    assert results["irl"]["fit"]["demonstrations_argmax"] is not None  # fitted, not judged
    # the faithful protocol judges it: test_tied_most_likely_actions_count_as_most_likely

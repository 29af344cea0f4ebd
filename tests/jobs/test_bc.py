"""``imitrl bc``'s report: the hint a clearly failing clone gets (issue 44)."""

from __future__ import annotations

from imitrl.jobs.bc import compounding_hint, report


def _ev(mean: float, lo: float | None, hi: float | None) -> dict:
    return {"mean_return": mean, "return_ci": [lo, hi], "episodes": 10,
            "exploration": "deterministic", "mean_length": 5.0}  # fmt: skip


def test_a_clone_clearly_below_the_expert_is_told_about_dagger():
    expert, failing = _ev(9000.0, 8990.0, 9010.0), _ev(120.0, 100.0, 140.0)
    assert "imitrl dagger" in compounding_hint(expert, failing)
    results = {"demonstrations": {"episodes": 1, "rows": 9, "source": "expert"},
               "final_loss": 0.5, "expert": expert, "learner": failing,
               "files": {"curves": "out/curves.png"}}  # fmt: skip
    lines = report(results)
    assert lines[-2] == compounding_hint(expert, failing) and lines[-1] == "wrote out"


def test_no_hint_where_the_clone_is_as_good_or_the_intervals_overlap():
    expert = _ev(500.0, 480.0, 520.0)
    assert compounding_hint(expert, _ev(500.0, 480.0, 520.0)) == ""
    assert compounding_hint(expert, _ev(470.0, 440.0, 485.0)) == ""  # overlapping: unclear
    assert compounding_hint(None, _ev(0.0, -1.0, 1.0)) == ""  # no expert to compare with
    assert compounding_hint(expert, _ev(10.0, None, None)) == ""  # one episode: no interval

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
               "learner_loss": "mse", "files": {"curves": "out/curves.png"}}  # fmt: skip
    lines = report(results)
    assert lines[-2] == compounding_hint(expert, failing) and lines[-1] == "wrote out"


def test_no_hint_where_the_clone_is_as_good_or_the_intervals_overlap():
    expert = _ev(500.0, 480.0, 520.0)
    assert compounding_hint(expert, _ev(500.0, 480.0, 520.0)) == ""
    assert compounding_hint(expert, _ev(470.0, 440.0, 485.0)) == ""  # overlapping: unclear
    assert compounding_hint(None, _ev(0.0, -1.0, 1.0)) == ""  # no expert to compare with
    assert compounding_hint(expert, _ev(10.0, None, None)) == ""  # one episode: no interval


def test_a_clone_at_random_level_is_told_how_to_tell_an_unfitted_clone_from_drift():
    """Issue 44: ACT and Diffusion Policy scored at random level on Pendulum and the only
    words were DAgger's; random actions on the same states flag it, and the training loss
    tells an unfitted clone (more steps) from one that drifts at once (DAgger: a newcomer's
    review, InvertedPendulum's clone at random level reached 1000 in one DAgger round)."""
    expert, failing = _ev(-121.0, -200.0, -41.0), _ev(-1300.0, -1581.0, -1020.0)
    random = _ev(-1102.5, -1377.3, -827.7)
    hint = compounding_hint(expert, failing, random)
    assert "random actions" in hint and "more --steps" in hint and "imitrl dagger" in hint
    assert "training loss" in hint  # what tells an unfitted clone from a drifting one
    chunked = compounding_hint(expert, failing, random, chunked=True)
    assert "plays predicted chunks" in chunked and "unchunked --loss" in chunked
    # a clone clearly above random actions but below the expert: compounding, DAgger
    assert "imitrl dagger" in compounding_hint(expert, _ev(-500.0, -600.0, -400.0), random)
    results = {"demonstrations": {"episodes": 1, "rows": 9, "source": "expert"},
               "final_loss": 0.5, "expert": expert, "learner": failing, "random": random,
               "learner_loss": "mse", "files": {"curves": "out/curves.png"}}  # fmt: skip
    lines = report(results)
    assert lines[-3].startswith("random actions: return -1102.50") and lines[-2] == hint
    assert report({**results, "learner_loss": "act"})[-2] == chunked


def test_the_bc_command_plays_random_actions_only_for_a_failing_clone(tmp_path):
    from imitrl.jobs.bc import run_bc
    from imitrl.jobs.configs import BCJob

    common = dict(env="Pendulum-v1", demos=2, eval_episodes=4, progress=False)
    failing = run_bc(BCJob(**common, num_steps=0, out=tmp_path / "a"))  # an untrained clone
    assert failing["random"]["episodes"] == 4 and failing["random"]["exploration"] == "random"
    again = run_bc(BCJob(**common, num_steps=0, out=tmp_path / "b"))
    assert again["random"] == failing["random"]  # the same draws from the same --eval-seed
    assert "random actions" in compounding_hint(failing["expert"], failing["learner"],
                                                failing["random"])  # fmt: skip

"""A loss that draws from its own generator saves it with the learner
(:class:`imitrl.rng.SavedGenerator`): a fit resumed from a checkpoint draws the noise,
time steps and latents the uninterrupted fit would have (a hostile review: ``diffusion``,
``flow``, ``mip``, ``act`` and the chunked entries resumed from the fresh seed)."""

from __future__ import annotations

import warnings

import pytest
import torch
from torchrl.objectives import LossModule

from imitrl.learners import build, registry
from imitrl.rng import SavedGenerator
from tests.learners.test_registry import TASKS, _rows

CONFIG = dict(hidden=(16, 16), lr=1e-2, seed=0)
TASK = TASKS["continuous"]


def _draws(name: str) -> bool:
    """Whether entry ``name``'s loss draws anything of its own."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loss = build(name, TASK, shared=CONFIG).loss
    return bool(_generators(loss))


def _generators(loss) -> list:
    """The loss modules in ``loss`` holding a generator (not a policy's own sampler)."""
    return [m for m in loss.modules() if isinstance(m, LossModule) and hasattr(m, "generator")]


# mse_l2 holds a generator for its entropy bonus, which draws only at entropy_coef > 0
# with a probabilistic actor (not its registry settings)
STOCHASTIC = [
    e.name
    for e in registry.entries()
    if e.applies_to(TASK) and e.name != "mse_l2" and _draws(e.name)
]


def test_the_stochastic_entries_are_the_ones_a_resume_must_continue():
    # the entries whose losses draw: each must save its generator (the next test)
    assert {"diffusion", "flow", "mip", "act", "diffusion_chunk", "diffusion_unet"} <= set(
        STOCHASTIC
    )


def _loss(learner, rows) -> torch.Tensor:
    out = learner.loss(rows)
    return sum(v for k, v in out.items() if k.startswith("loss_"))


@pytest.mark.parametrize("name", STOCHASTIC)
def test_a_learner_loaded_from_a_state_continues_its_draws(name):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = build(name, TASK, shared=CONFIG)
        b = build(name, TASK, shared=CONFIG)
    rows = a.training_rows(_rows(TASK))
    first = _loss(a, rows)
    state = a.state_dict()
    second = _loss(a, rows)
    assert not torch.equal(first, second)  # each step draws afresh
    b.load_state_dict(state)
    assert torch.equal(_loss(b, rows), second)  # was ``first``: b drew from its seed again
    assert all(isinstance(m, SavedGenerator) for m in _generators(b.loss))


@pytest.mark.parametrize(
    "bad",
    [torch.zeros(3), torch.zeros(10, dtype=torch.uint8), torch.zeros(5056, 1, dtype=torch.uint8),
     torch.zeros(5056, dtype=torch.uint8).to_sparse(), "state"],
    ids=["float", "short", "2-d", "sparse", "text"],
)  # fmt: skip
def test_a_generator_state_of_the_wrong_kind_is_refused_in_one_line(bad, tmp_path):
    """Two hostile reviews: a float state, a sparse one (a ``TypeError`` traceback) or one
    of the wrong size (blamed on the env) in ``learner.pt``."""
    from tests._cli import run_main

    learner = build("flow", TASK, shared=CONFIG)
    state = learner.state_dict()
    state["loss._extra_state"] = bad
    with pytest.raises(
        ValueError, match=r"FlowMatchingLoss's _extra_state\) must be a dense uint8"
    ):
        learner.load_state_dict(state)
    run = tmp_path / "run"
    flags = ["--env", "Pendulum-v1", "--loss", "flow", "--hidden", "16,16", "--demos", "1",
             "--steps", "5", "--max-episode-steps", "20", "--eval-episodes", "1", "--no-progress"]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert run_main("bc", *flags, "--out", str(run))[0] == 0
    saved = torch.load(run / "learner.pt", weights_only=True)
    saved["loss._extra_state"] = bad
    torch.save(saved, run / "learner.pt")
    status, _, err = run_main("eval", "--checkpoint", str(run), "--no-progress")
    assert status == 2 and "must be a dense uint8 tensor" in err and "Traceback" not in err, err


def test_a_state_without_generators_keeps_the_fresh_seed():
    """What imitrl up to e0ceebc saved: the migration keeps the freshly seeded generator."""
    learner = build("flow", TASK, shared=CONFIG)
    old = {k: v for k, v in learner.state_dict().items() if not k.endswith("_extra_state")}
    migrated = learner.migrated_state({"learner": old})["learner"]
    fresh = build("flow", TASK, shared=CONFIG)
    fresh.load_state_dict(migrated)
    rows = fresh.training_rows(_rows(TASK))
    assert torch.equal(_loss(fresh, rows), _loss(learner, rows))


def test_a_sampling_learners_dagger_resumes_to_the_uninterrupted_run(tmp_path):
    """A flow learner acts by drawing from its policy's own generator (``RANDOM``): saved
    with the learner too, a resumed DAgger's rollouts and evaluations draw what the
    uninterrupted run's did (was: round 2 after a resume from round 1 differed)."""
    import json
    import shutil

    from tests._cli import run_main

    flags = ["dagger", "--env", "Pendulum-v1", "--loss", "flow", "--hidden", "16,16",
             "--demos", "1", "--max-episode-steps", "50", "--eval-episodes", "2",
             "--steps", "20", "--episodes-per-round", "1", "--no-progress"]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert run_main(*flags, "--rounds", "3", "--out", str(tmp_path / "whole"))[0] == 0
        assert run_main(*flags, "--rounds", "2", "--out", str(tmp_path / "part"))[0] == 0
        status, _, err = run_main(*flags, "--rounds", "3", "--out", str(tmp_path / "part"),
                                  "--resume")  # fmt: skip
        assert status == 0, err
        shutil.copytree(tmp_path / "whole", tmp_path / "again")  # a finished run resumed
        status, _, err = run_main(*flags, "--rounds", "3", "--out", str(tmp_path / "again"),
                                  "--resume")  # fmt: skip
    assert status == 0, err
    whole, part = (
        json.loads((tmp_path / p / "results.json").read_text()) for p in ("whole", "part")
    )
    assert [r["evaluation"] for r in part["rounds"]] == [r["evaluation"] for r in whole["rounds"]]
    assert part["learner"] == whole["learner"] and part["final_loss"] == whole["final_loss"]
    # imitrl eval replays the last round's evaluation: learner.pt holds the learner as
    # fitted, before that evaluation drew from its generator (a hostile review: it differed)
    for run in ("whole", "part", "again"):
        status, _, err = run_main("eval", "--checkpoint", str(tmp_path / run), "--no-progress",
                                  "--out", str(tmp_path / f"{run}-eval"))  # fmt: skip
        assert status == 0, err
        ev = json.loads((tmp_path / f"{run}-eval" / "eval.json").read_text())["evaluation"]
        assert ev == whole["learner"], run


def test_generators_kept_replays_a_sampling_policys_evaluation():
    """A hostile review: a flow learner evaluated twice with one seed (or one fresh
    generator) scored -3280.7 then -4145.7: it samples from its own generator, which
    advances. In generators_kept the draws replay, and the learner's stream is as before."""
    from torchrl.envs.utils import ExplorationType

    from imitrl.envs import make_env
    from imitrl.evaluation import evaluate
    from imitrl.rng import generators_kept

    learner = build("flow", make_env("Pendulum-v1", seed=0), hidden=(8,), seed=0)

    def score():
        env = make_env("Pendulum-v1", seed=5, max_episode_steps=10)
        return evaluate(env, learner, 2, seed=5, exploration=ExplorationType.RANDOM).mean_return

    before = [m.generator.get_state() for m in learner.modules() if isinstance(m, SavedGenerator)]
    with generators_kept(learner):
        first = score()
    with generators_kept(learner):
        assert score() == first
    after = [m.generator.get_state() for m in learner.modules() if isinstance(m, SavedGenerator)]
    assert before and all(torch.equal(a, b) for a, b in zip(before, after))
    assert score() == first and score() != first  # outside it, the stream advances

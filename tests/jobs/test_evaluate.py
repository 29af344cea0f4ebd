"""``imitrl eval``: a checkpoint's evaluation reproduces its own run's, whatever job made it."""

from __future__ import annotations

import pytest

from imitrl.jobs.configs import AIRLJob, GAILJob
from imitrl.jobs.evaluate import EvalJob, run_eval

TINY = dict(total_steps=256, rollout_steps=128, ppo_epochs=2, minibatch_size=64,
            discriminator_updates=2, discriminator_batch=32, demos=1, num_envs=2,
            max_episode_steps=50, eval_every=0, progress=False)  # fmt: skip


@pytest.mark.parametrize("job", [GAILJob, AIRLJob])
def test_eval_of_an_adversarial_run_reproduces_its_evaluation(job, tmp_path):
    """Issue 44: ``imitrl eval`` played 10 episodes where gail/airl had evaluated 20, so
    their numbers did not reproduce; with no --eval-episodes or --eval-seed it now plays
    the run's own."""
    from imitrl.jobs.gail import run_airl, run_gail

    out = tmp_path / "run"
    run = run_airl if job is AIRLJob else run_gail
    results = run(job(out=out, eval_seed=123, **TINY))
    assert results["learner"]["episodes"] == job.eval_episodes == 20  # the jobs' default
    ev = run_eval(EvalJob(checkpoint=out, progress=False))["evaluation"]
    assert ev["episodes"] == 20
    assert ev["mean_return"] == results["learner"]["mean_return"]
    other = run_eval(EvalJob(checkpoint=out, eval_episodes=3, eval_seed=5, progress=False))
    assert other["evaluation"]["episodes"] == 3  # given flags still win


def test_eval_of_a_diffusion_policy_run_reproduces_its_evaluation(tmp_path):
    """Issue 44: Diffusion Policy sampled from a generator of its own, which the run's
    evaluation advanced before the checkpoint saved it, so ``imitrl eval`` drew other
    samples (-1096.52 against the run's -1111.20); it now draws from the RNG the
    evaluation seeds, as every sampled policy does."""
    from imitrl.jobs.bc import run_bc
    from imitrl.jobs.configs import BCJob

    out = tmp_path / "run"
    results = run_bc(BCJob(env="Pendulum-v1", loss="diffusion_unet", demos=1, num_steps=3,
                           batch_size=16, eval_episodes=3, max_episode_steps=20,
                           progress=False, out=out))  # fmt: skip
    saved = results["learner"]
    assert saved["exploration"] == "random" and saved["return_ci"][0] < saved["return_ci"][1]
    assert run_eval(EvalJob(checkpoint=out, progress=False))["evaluation"] == saved
    assert run_eval(EvalJob(checkpoint=out, progress=False))["evaluation"] == saved  # again

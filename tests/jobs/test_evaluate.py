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


def test_eval_json_records_what_was_evaluated(tmp_path):
    """A hostile review: eval.json named neither the checkpoint, nor the time limit, nor the
    env's arguments, so two evaluations of other settings could not be told apart."""
    import json

    from imitrl.jobs.bc import run_bc
    from imitrl.jobs.configs import BCJob

    out = tmp_path / "run"
    run_bc(BCJob(env="CartPole-v1", demos=1, num_steps=2, batch_size=8, eval_episodes=1,
                 max_episode_steps=30, progress=False, out=out))  # fmt: skip
    run_eval(EvalJob(checkpoint=out, max_episode_steps=7, eval_episodes=1, progress=False,
                     env_kwargs=(("sutton_barto_reward", True),), out=tmp_path / "e"))  # fmt: skip
    said = json.loads((tmp_path / "e" / "eval.json").read_text())
    assert said["checkpoint"] == str(out) and said["max_episode_steps"] == 7
    assert said["env_kwargs"] == {"sutton_barto_reward": True}
    expert = run_eval(EvalJob(expert="cartpole", env="CartPole-v1", eval_episodes=1,
                              progress=False))  # fmt: skip
    assert expert["checkpoint"] is None and expert["max_episode_steps"] == 500


def test_the_metaworld_expert_evaluates_under_lerobots_observation_types():
    """A hostile review: its state was looked up under 'observation', which LeRobot's
    obs types give the 4-d hand alone (bc and dagger passed the env; eval did not)."""
    pytest.importorskip("metaworld")
    got = run_eval(EvalJob(expert="metaworld", env="metaworld/reach-v3", eval_episodes=1,
                           max_episode_steps=60, progress=False,
                           env_kwargs=(("obs_type", "environment_state_agent_pos"),)))  # fmt: skip
    assert got["evaluation"]["success_rate"] == 1.0


def test_an_env_kwarg_given_to_eval_or_compare_goes_over_the_runs_own(tmp_path):
    """A hostile review: one --env-kwarg (even one of the run's own) dropped all of the
    run's others, and the default lake was played without a word (return 0 for 1); a
    lake given as rows of letters (lists) trained, then its checkpoint was refused."""
    from tests._cli import run_main

    out = tmp_path / "lake"
    status, _, err = run_main("bc", "--env", "FrozenLake-v1", "--env-kwarg",
                              "desc=[['S','F','F','F'],['F','F','F','F'],['F','H','H','H'],"
                              "['F','F','F','G']]", "--env-kwarg", "is_slippery=false",
                              "--demos", "1", "--steps", "200", "--eval-episodes", "2",
                              "--no-progress", "--out", str(out))  # fmt: skip
    assert status == 0, err
    status, printed, err = run_main("eval", "--checkpoint", str(out), "--env-kwarg",
                                    "is_slippery=false", "--no-progress")  # fmt: skip
    assert status == 0, err
    assert "(desc=[['S', 'F', 'F', 'F'], " in printed and "is_slippery=False)" in printed
    assert "return 1.00 [1.00, 1.00] over 2 episodes" in printed and "length 6.0" in printed
    status, printed, err = run_main("compare", "--a", "expert", "--b", str(out), "--env-kwarg",
                                    "is_slippery=false", "--episodes", "2")  # fmt: skip
    assert status == 0 and "return: a 1, b 1" in printed and "(desc=" in printed, err

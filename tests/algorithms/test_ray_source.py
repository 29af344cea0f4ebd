"""DAgger on Ray workers (RaySource): same seed and workers, same rows; a dying worker.

Starting Ray and its worker actors costs most of this module's time on 2 cores, so
one local Ray instance serves the module and one RaySource (2 workers) plays three
DAgger runs: a clean run, its repeat (the workers' earlier rounds must not leak into
the rows), and a run in which one worker's env kills its process mid-round (armed by
a file the test creates). The CLI job starts one more worker of its own.
"""

from __future__ import annotations

import functools
import os
import sys

import pytest
import torch
from torchrl.envs import Transform, TransformedEnv
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, Constant, DAggerConfig, dagger
from imitrl.data import DemonstrationBuffer
from imitrl.data.chunks import IS_INIT
from imitrl.envs import make_env
from imitrl.experts import cartpole_expert
from imitrl.policies import BetaMixer, behaviour_policy
from imitrl.runtime import rollout_episodes
from imitrl.system import OnDevice

ray = pytest.importorskip("ray")
from imitrl.algorithms.ray_source import (  # noqa: E402
    WORKER_THREADS,
    RaySource,
    init_ray,
    worker_env,
    worker_policy,
)
from imitrl.cli import build_parser  # noqa: E402
from imitrl.cli.flags import config_from_args  # noqa: E402
from imitrl.jobs.dagger import DAggerJob  # noqa: E402
from imitrl.jobs.dagger import run_dagger as run_dagger_job  # noqa: E402
from imitrl.learners import TaskSpec, build  # noqa: E402

WORKERS = 2


@pytest.fixture(scope="module")
def ray_session():
    started = init_ray(WORKERS + 1)  # + 1: the CLI job's worker
    yield
    if started:
        ray.shutdown()


class _ExitWhenArmed(Transform):
    """Once ``armed`` exists, kills its process at its next env step, in the first process
    to get there (the one that creates ``fired``): exactly one worker dies, mid-round."""

    def __init__(self, armed: str, fired: str) -> None:
        super().__init__()
        self.armed, self.fired = armed, fired

    def _step(self, tensordict, next_tensordict):
        if os.path.exists(self.armed):
            try:
                os.close(os.open(self.fired, os.O_CREAT | os.O_EXCL))
            except FileExistsError:
                return next_tensordict
            os._exit(1)
        return next_tensordict


def cartpole_with_fault(armed: str, fired: str, *, seed: int):
    return TransformedEnv(make_env("CartPole-v1", seed=seed), _ExitWhenArmed(armed, fired))


def _learner(env):
    learner = build("for_env", env, hidden=(16,), seed=0)
    learner.exploration = ExplorationType.RANDOM  # the workers' torch RNG is exercised
    return learner


def run_dagger(source: RaySource) -> torch.Tensor:
    """2-round DAgger (one relabel round of 5 episodes, beta 0.5) on CartPole; the buffer."""
    env = make_env("CartPole-v1", seed=0)
    expert = cartpole_expert()
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, expert, 1))
    config = DAggerConfig(
        rounds=2, episodes_per_round=5, beta=Constant(0.5), bc=BCConfig(num_steps=5), seed=0
    )
    dagger(source, expert, lambda: _learner(env), buffer, config)
    return buffer.data


def assert_whole_episodes(rows) -> None:
    """Every episode: steps 0..len-1 in order, done at its last step and nowhere else."""
    episodes = rows[keys.EPISODE]
    for e in episodes.unique().tolist():
        ep = rows[episodes == e]
        assert torch.equal(ep[keys.STEP], torch.arange(ep.shape[0]))
        done = ep[keys.NEXT, keys.DONE].reshape(-1)
        assert done[-1] and not done[:-1].any()


@pytest.fixture(scope="module")
def fault_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fault")
    return str(folder / "armed"), str(folder / "fired")


@pytest.fixture(scope="module")
def source(ray_session, fault_files):
    env_fn = functools.partial(cartpole_with_fault, *fault_files, seed=0)
    with RaySource(env_fn, WORKERS, seed=3) as source:
        yield source


@pytest.fixture(scope="module")
def clean_rows(source):
    return run_dagger(source)


def test_same_seed_and_workers_give_identical_rows(source, clean_rows):
    again = run_dagger(source)
    relabelled = clean_rows[clean_rows[keys.ROUND] == 1]
    assert relabelled.shape[0] > 5  # 5 whole episodes
    assert relabelled[keys.EPISODE].unique().numel() == 5
    assert 0 < relabelled[keys.EXPERT_EXECUTED].float().mean() < 1  # coins were flipped
    assert set(clean_rows.keys(True, True)) == set(again.keys(True, True))
    for key in clean_rows.keys(True, True):
        assert torch.equal(clean_rows[key], again[key]), key
    order = (
        clean_rows[keys.ROUND] * 10**6 + clean_rows[keys.EPISODE] * 10**3 + clean_rows[keys.STEP]
    )
    assert bool((order.diff() > 0).all())  # (round, worker slot, episode, step) order
    assert_whole_episodes(clean_rows)


def test_evaluation_runs_on_the_workers(source, clean_rows):
    env = make_env("CartPole-v1", seed=0)
    learner, expert = _learner(env), cartpole_expert()
    source.check(expert, learner)
    first = source.evaluate(expert, learner, 3, seed=1)
    again = source.evaluate(expert, learner, 3, seed=1)
    assert first.returns.shape == (3,) and bool((first.lengths > 0).all())
    assert torch.equal(first.returns, first.lengths.double())  # CartPole: 1 per step
    assert torch.equal(first.returns, again.returns)


def test_workers_act_on_the_cpu_with_one_torch_thread(source, clean_rows):
    """After DAgger's rounds (weights broadcast twice), every worker's process runs one
    torch thread and holds its policy's parameters on the CPU."""
    actors = source._collector.remote_collectors
    refs = [
        actors[a].__ray_call__.remote(
            lambda collector: (
                torch.get_num_threads(),
                {p.device.type for p in collector.policy.parameters()},
            )
        )
        for a in range(WORKERS)
    ]
    assert ray.get(refs) == [(1, {"cpu"})] * WORKERS and WORKER_THREADS == 1


def test_the_workers_copy_of_the_policy_is_on_the_cpu_with_the_drivers_keys():
    """What lets a learner on CUDA drive CPU workers, checked without CUDA: an
    ``OnDevice`` wrapper that says another device (``meta`` stands for ``cuda``)."""
    from tensordict import TensorDict

    env = make_env("CartPole-v1", seed=0)
    wrapped = OnDevice(_learner(env).policy, torch.device("meta"))
    mixer = BetaMixer(0.5, generator=torch.Generator().manual_seed(0))
    behaviour = behaviour_policy(cartpole_expert(), wrapped, mixer)
    copy = worker_policy(behaviour)
    (on,) = [m for m in copy.modules() if isinstance(m, OnDevice)]
    assert on.device == torch.device("cpu") and wrapped.device == torch.device("meta")
    assert {p.device.type for p in copy.parameters()} == {"cpu"}
    (copied_mixer,) = [m for m in copy.modules() if isinstance(m, BetaMixer)]
    assert copied_mixer.generator is None and mixer.generator is not None
    keys_of = lambda m: set(TensorDict.from_module(m).keys(True, True))  # noqa: E731
    assert keys_of(copy) == keys_of(behaviour)  # the driver's weights load as they are


def test_a_worker_dying_mid_round_replays_its_slot(source, clean_rows, fault_files):
    armed, fired = fault_files
    open(armed, "w").close()
    with pytest.warns(RuntimeWarning, match="died"):
        rows = run_dagger(source)
    assert os.path.exists(fired)  # the fault fired: one worker is left
    assert source.live_workers == WORKERS - 1
    assert_whole_episodes(rows)
    for key in clean_rows.keys(True, True):  # the round completed as if undisturbed
        assert torch.equal(clean_rows[key], rows[key]), key


def test_the_cli_job_runs_dagger_on_workers(ray_session, tmp_path):
    job = DAggerJob(
        env="CartPole-v1", demos=1, rounds=2, episodes_per_round=2, num_steps=5, hidden=(8,),
        eval_episodes=2, out=tmp_path, progress=False, workers=1,
    )  # fmt: skip
    results = run_dagger_job(job)
    assert results["rounds"][0]["rows_collected"] > 0
    args = build_parser().parse_args(["dagger", "--workers", "3", "--address", "auto"])
    parsed = config_from_args(DAggerJob, args)
    assert (parsed.workers, parsed.address) == (3, "auto")
    with pytest.raises(ValueError, match="--workers"):
        DAggerJob(address="auto")


def test_a_chunked_learner_runs_on_workers_with_the_users_plain_env(ray_session, tmp_path):
    """A chunked learner reads ``is_init``; Pendulum does not write it. The workers wrap
    their env in TorchRL's InitTracker as a local rollout does (without it the worker's
    first step raises): DAgger's relabel round and the evaluation run on a worker."""
    env_fn = functools.partial(make_env, "Pendulum-v1", seed=0)
    plain = make_env("Pendulum-v1", seed=0)
    task = TaskSpec(action=plain.action_spec_unbatched, observation_dim=3)
    chunked = build("mse_chunk", task, shared=dict(hidden=(8,)))

    flat = build("mse", task, shared=dict(hidden=(8,)))
    assert worker_env(env_fn, plain, flat.policy) is env_fn
    tracked = worker_env(env_fn, plain, chunked.policy)()
    assert bool(tracked.reset().get(IS_INIT).all())
    job = DAggerJob(
        env="Pendulum-v1", loss="mse_chunk", demos=1, rounds=2, episodes_per_round=1,
        num_steps=5, hidden=(8,), eval_episodes=1, out=tmp_path, progress=False, workers=1,
    )  # fmt: skip
    results = run_dagger_job(job)
    # round 0 relabels one whole episode (200 steps) the initial fit drove; the last fits only
    assert [r["rows_collected"] for r in results["rounds"]] == [200, 0]


class _RaiseOnStep(Transform):
    """An env that refuses its first step (a user's bug, not a dying process)."""

    def _step(self, tensordict, next_tensordict):
        raise ValueError("the env refuses to step")


def cartpole_that_raises(*, seed: int):
    return TransformedEnv(make_env("CartPole-v1", seed=seed), _RaiseOnStep())


def test_an_error_in_a_worker_is_raised_in_the_driver_with_its_message(ray_session):
    """Ray 2.x turns an exception in an actor's call into a dead worker (its error store
    fails), which would read as "all workers died"; the worker returns it instead, and
    the driver raises the same type with the worker's message. No row is added."""
    env = make_env("CartPole-v1", seed=0)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, cartpole_expert(), 1))
    before = len(buffer)
    config = DAggerConfig(rounds=2, episodes_per_round=1, bc=BCConfig(num_steps=2), seed=0)
    make = functools.partial(cartpole_that_raises, seed=0)
    with RaySource(make, 1, seed=0) as src:
        with pytest.raises(ValueError, match="slot 0 failed: ValueError: the env refuses"):
            dagger(src, cartpole_expert(), lambda: _learner(env), buffer, config)
        assert src.live_workers == 1  # the worker is alive, not replayed elsewhere
    assert len(buffer) == before


def test_missing_ray_gives_the_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    with pytest.raises(ImportError, match=r"imitrl\[distributed\]"):
        RaySource(functools.partial(make_env, "CartPole-v1", seed=0), 2)

"""The seam (:mod:`imitrl.runtime.paths`): its accelerated paths give the reference's digits.

Every accelerated piece lives in :mod:`imitrl.runtime.fast` and is reached only through
the seam; each has a reference on public TorchRL/torch. The tests here run the same
calls both ways and ask for identical results (values, dtypes, shapes):

* rollouts and evaluations: the accelerated stepper (the simulator stepped directly,
  ``imitrl.runtime.fast.env_steps``; the policy called on a dict of tensors,
  ``TensorPolicy``) and, for evaluations of gymnasium's toy-text envs, the stream player,
  against the same calls inside ``paths.reference()`` (every step through ``env.step_and_maybe_reset`` and
  ``policy(td)``), including the episodes played next: the env's random state must end
  where TorchRL's path leaves it;
* fits and the seam itself: ``test_paths_seam.py``.
"""

from __future__ import annotations

import contextlib

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs.utils import ExplorationType, set_exploration_type

import imitrl.runtime.fast.toy_text as toy_text_module
from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.envs import TabularEnv, make_env
from imitrl.evaluation import evaluate
from imitrl.experts import cartpole_expert, pendulum_expert
from imitrl.learners import ActorCritic, TaskSpec, build
from imitrl.policies import Expert
from imitrl.policies.mixture import BetaMixer, behaviour_policy
from imitrl.runtime import episode_returns, paths, rollout_episodes
from imitrl.runtime.fast.env_steps import direct_steps
from imitrl.runtime.fast.policy_call import TensorPolicy, direct_call
from imitrl.tabular import TabularMDP, greedy, value_iteration

DET, RND, MODE = ExplorationType.DETERMINISTIC, ExplorationType.RANDOM, ExplorationType.MODE


def assert_same(a, b) -> None:
    """Identical TensorDicts, tensors or summaries: keys, dtypes, shapes and every value."""
    if isinstance(a, TensorDict):
        assert sorted(a.keys(True, True), key=str) == sorted(b.keys(True, True), key=str)
        assert a.batch_size == b.batch_size
        for k in a.keys(True, True):
            assert_same(a.get(k), b.get(k))
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape
        if a.is_floating_point():  # NaN where the other has NaN, equal values elsewhere
            nan = a.isnan()
            assert torch.equal(nan, b.isnan()) and torch.equal(a[~nan], b[~nan])
        else:
            assert torch.equal(a, b)
    elif a is None:
        assert b is None
    else:
        for field in ("returns", "lengths", "success"):
            assert_same(getattr(a, field), getattr(b, field))


def _point_mass():
    """A point mass with float32 observations and a float64 action box."""

    class PointMass(gym.Env):
        observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float64)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.s = self.np_random.uniform(-1, 1, size=2)
            return self.s.astype(np.float32), {}

        def step(self, u):
            x, v = self.s
            v = v + 0.1 * float(np.clip(u[0], -1, 1))
            self.s = np.array([x + 0.1 * v, v])
            return self.s.astype(np.float32), -x * x, bool(abs(x) > 0.9), False, {}

    return PointMass()


gym.register("imitrl-test/FastPathF64-v0", entry_point=_point_mass, max_episode_steps=25)


def _f64_expert() -> Expert:
    return Expert.from_callable(lambda obs: -obs[..., 1:2].double())


# every env make_env hands to the direct path: float32 and float64 (MuJoCo) observations,
# float64 actions, discrete and continuous actions, one lane and several
GYM_CASES = [
    ("CartPole-v1", cartpole_expert, 40),
    ("Pendulum-v1", pendulum_expert, 30),
    ("imitrl-test/FastPathF64-v0", _f64_expert, None),
]


@pytest.fixture(scope="module")
def lake_q(lake: TabularMDP) -> torch.Tensor:
    return lake.backup(value_iteration(lake, 300)[-1])


def _learner(env, head=None, exploration=DET) -> ActorCritic:
    learner = build("for_env", env, seed=1, hidden=(16, 16), head=head)
    learner.exploration = exploration
    return learner


def _on(fast: bool, run, *args):
    """``run(*args)`` on the accelerated paths, or inside ``paths.reference()``."""
    with contextlib.nullcontext() if fast else paths.reference():
        return run(*args)


def _rollouts_on_both_paths(make, run) -> None:
    """``run(env)`` on two fresh copies of an env, each path on one, twice each (the
    second call continues from the random state the first left): identical results."""
    fast_env, slow_env = make(), make()
    for _ in range(2):
        assert_same(_on(True, run, fast_env), _on(False, run, slow_env))


# ------------------------------------------------------------------ the env step
@pytest.mark.parametrize(("env_id", "make_expert", "limit"), GYM_CASES)
@pytest.mark.parametrize("lanes", [1, 3])
def test_direct_rows_equal_torchrl_rows(env_id, make_expert, limit, lanes):
    def make():
        return make_env(env_id, seed=2, num_envs=lanes, max_episode_steps=limit)

    env = make()
    assert direct_steps(env) is not None
    expert = make_expert()
    learner = _learner(env)

    def run(env):
        mixer = BetaMixer(0.5, generator=torch.Generator().manual_seed(4))
        behaviour = behaviour_policy(expert, learner.policy, mixer)
        demos = rollout_episodes(env, expert, 3)
        rows = rollout_episodes(env, behaviour, 4, exploration=DET, round_index=1)
        return TensorDict({"demos": demos, "rows": rows}, batch_size=[])

    _rollouts_on_both_paths(make, run)


def test_float64_observations_take_the_direct_path_and_agree():
    pytest.importorskip("mujoco")
    for lanes in (1, 2):

        def make(lanes=lanes):
            return make_env("InvertedPendulum-v5", seed=0, num_envs=lanes, max_episode_steps=20)

        learner = _learner(make())
        assert direct_steps(make()) is not None
        expert = _f64_expert().bind(make().action_spec_unbatched)

        def run(env, learner=learner, expert=expert):
            rows = rollout_episodes(
                env,
                behaviour_policy(expert, learner.policy, BetaMixer(0.0)),
                3,
                exploration=DET,
            )
            assert rows.get(keys.OBSERVATION).dtype == torch.float32
            return rows

        _rollouts_on_both_paths(make, run)


@pytest.mark.parametrize("rng", ["torch", "gymnasium"])
@pytest.mark.parametrize("lanes", [(), (4,)])
def test_tabular_env_direct_path_equals_torchrl(lake, lake_q, rng, lanes):
    def make():
        return TabularEnv(lake, batch_size=lanes, seed=3, rng=rng)

    expert = Expert.from_q(lake_q)
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))
    learner.exploration = RND

    def run(env):
        mixer = BetaMixer(0.3, generator=torch.Generator().manual_seed(1))
        rows = rollout_episodes(
            env,
            behaviour_policy(expert, learner.policy, mixer),
            5,
            exploration=RND,
            generator=torch.Generator().manual_seed(2),
        )
        ev = evaluate(env, expert, 9)  # success_fn: the goal states
        return TensorDict(
            {"rows": rows, "success": ev.success_rate, "ret": ev.mean_return}, batch_size=[]
        )

    _rollouts_on_both_paths(make, run)


@pytest.mark.parametrize("lanes", [1, 3])
def test_sampled_and_success_returns_equal_torchrl(lanes):
    """A sampled learner (its draws replayed from the seeded generator)
    and a success criterion (the step tensordict rebuilt where an episode ends)."""

    def make():
        return make_env("Pendulum-v1", seed=5, num_envs=lanes, max_episode_steps=20)

    learner = _learner(make(), head="normal", exploration=RND)

    def success(out):
        return out.get((keys.NEXT, keys.OBSERVATION))[..., 0] > 0

    def run(env):
        return episode_returns(
            env,
            learner.policy,
            5,
            exploration=RND,
            success_fn=success,
            generator=torch.Generator().manual_seed(9),
        )

    _rollouts_on_both_paths(make, run)


def test_dagger_rounds_equal_torchrl():
    def run():
        env = make_env("CartPole-v1", seed=0, num_envs=2, max_episode_steps=30)
        expert = cartpole_expert()
        buffer = DemonstrationBuffer(action_spec=env.action_spec)
        buffer.extend(rollout_episodes(env, expert, 2))
        config = DAggerConfig(
            rounds=3, episodes_per_round=2, beta=lambda k: 0.5, bc=BCConfig(num_steps=20)
        )
        source = EnvSource(env)
        result = dagger(source, expert, lambda: _learner(env), buffer, config)
        return result.buffer.data, result.learner.state_dict()

    (fast, fast_weights), (slow, slow_weights) = _on(True, run), _on(False, run)
    assert_same(fast, slow)
    assert all(torch.equal(fast_weights[k], slow_weights[k]) for k in fast_weights)


def test_envs_the_direct_path_does_not_take():
    assert direct_steps(make_env("CartPole-v1", seed=0, frame_skip=2)) is None
    env = make_env("CartPole-v1", seed=0)
    assert direct_steps(env.append_transform(_step_counter())) is None


def _step_counter():
    from torchrl.envs import StepCounter

    return StepCounter()


def test_errors_are_the_same_on_both_paths():
    env = make_env("CartPole-v1", seed=0, max_episode_steps=50)
    bad = TensorDictModule(lambda o: torch.zeros(2, dtype=torch.int64), ["observation"], ["action"])
    calls = [
        ("ran past max_steps=5 steps", lambda: episode_returns(env, cartpole_expert(), 2, max_steps=5)),
        ("must write 'expert_action'",
         lambda: rollout_episodes(env, _learner(env).policy, 1, exploration=DET)),
        (r"the policy's action has dtype torch\.int64, shape \(2,\)",
         lambda: episode_returns(env, bad, 1, exploration=DET)),
    ]  # fmt: skip
    for fast in (True, False):
        for match, call in calls:
            with pytest.raises(ValueError, match=match):
                _on(fast, call)


# ------------------------------------------------------------------ the policy call
def _policies():
    cart, pend = make_env("CartPole-v1", seed=0), make_env("Pendulum-v1", seed=0, num_envs=3)
    lake_env = make_env("FrozenLake-v1", seed=0, num_envs=2)
    yield cart, _learner(cart).policy
    yield lake_env, _learner(lake_env).policy
    yield lake_env, build("cross_entropy", TaskSpec(action=4, num_states=16)).policy
    for head in ("deterministic", "normal", "tanh_normal", "normal_free", "tanh_normal_free"):
        yield pend, _learner(pend, head=head).policy
    expert = cartpole_expert()
    expert.bind(cart.action_spec_unbatched)
    yield cart, expert.as_actor()
    yield cart, behaviour_policy(expert, _learner(cart).policy, BetaMixer(1.0))
    yield cart, Expert.from_policy(_learner(cart).policy).as_actor()  # a label of a policy


@pytest.mark.parametrize("exploration", [DET, MODE, RND])
def test_policy_replay_equals_the_tensordict_call(exploration):
    """Every module replayed, none run through forward; a sampled actor (RANDOM) draws
    the same numbers from the global RNG as its own forward does."""
    for env, policy in _policies():
        td = env.reset()
        with torch.no_grad(), set_exploration_type(exploration):
            replay = TensorPolicy(policy, env.batch_size)
            assert not replay.opaque
            values = dict(td.items(True, True))
            try:
                torch.manual_seed(11)
                out = policy(td.clone())
            except RuntimeError as err:  # TanhNormal has no mode: the replay says so too
                with pytest.raises(RuntimeError, match="has not analytical mode"):
                    replay(values)
                assert "has not analytical mode" in str(err)
                continue
            torch.manual_seed(11)
            replay(values)
        assert_same(TensorDict(values, batch_size=env.batch_size), out)


def test_mixer_coins_and_opaque_modules_are_the_modules_own():
    env = make_env("Pendulum-v1", seed=0, num_envs=4)
    learner = _learner(env, head="normal")
    outside = TensorDictSequential(
        TensorDictModule(lambda o: o * 2, [keys.OBSERVATION], ["twice"]),
    ).select_out_keys("twice")  # selected out-keys: run through its own forward
    for sample in (DET, RND):
        td = env.reset()
        with torch.no_grad(), set_exploration_type(sample):
            outputs = []
            for replayed in (True, False):
                torch.manual_seed(0)
                mixer = BetaMixer(0.5, generator=torch.Generator().manual_seed(3))
                policy = TensorDictSequential(
                    behaviour_policy(pendulum_expert(), learner.policy, mixer), outside
                )
                if replayed:
                    step = TensorPolicy(policy, env.batch_size)
                    assert step.opaque and step.draws
                    values = dict(td.items(True, True))
                    step(values)
                    outputs.append(TensorDict(values, batch_size=env.batch_size))
                else:
                    outputs.append(policy(td.clone()))
        assert_same(*outputs)


# ------------------------------------------------------- toy-text evaluations by the stream
TOY_TEXT = [("FrozenLake-v1", None), ("Taxi-v4", 60), ("CliffWalking-v1", 60)]


@pytest.mark.parametrize(("env_id", "limit"), TOY_TEXT)
@pytest.mark.parametrize("lanes", [1, 3])
def test_toy_text_evaluation_by_the_stream_equals_stepping(env_id, limit, lanes, monkeypatch):
    mdp = TabularMDP.from_gym(env_id, 0.95)
    table = greedy(mdp.backup(value_iteration(mdp, 200)[-1]))

    def make():
        return make_env(env_id, seed=7, num_envs=lanes, max_episode_steps=limit)

    learner = _learner(make())  # an MLP over one-hot states, greedy
    streamed = []
    play_lanes = toy_text_module.play_lanes
    monkeypatch.setattr(
        toy_text_module, "play_lanes", lambda *a: streamed.append(1) or play_lanes(*a)
    )

    def run(env):
        out = [
            episode_returns(env, Expert.from_table(table), 11, seed=1),
            episode_returns(env, learner.policy, 4, exploration=DET),
            episode_returns(env, Expert.from_table(table), 5),
        ]
        # the episodes a step-by-step rollout plays next, from the generators left behind
        with paths.reference():
            rows = rollout_episodes(env, Expert.from_table(table), 2)
        return [*out, rows]

    fast_env, slow_env = make(), make()
    for _ in range(2):
        for a, b in zip(_on(True, run, fast_env), _on(False, run, slow_env)):
            assert_same(a, b)
    assert len(streamed) == 6  # every fast evaluation went through the stream


def test_the_stream_is_skipped_where_it_cannot_replace_the_steps(lake_q, monkeypatch):
    monkeypatch.setattr(toy_text_module, "play_lanes", None)  # would fail if called
    env = make_env("FrozenLake-v1", seed=0)
    learner = _learner(env, exploration=RND)
    episode_returns(env, learner.policy, 3, exploration=RND)  # samples: not a table
    episode_returns(env, Expert.from_q(lake_q), 3, success_fn=lambda out: out["done"])


def module_width(module) -> int:
    """The input width a test module takes (2: Squash's bounds, 3: the normaliser's)."""
    shape = getattr(module, "shape", None) or getattr(module, "low", torch.zeros(5)).shape
    return int(shape[0])


def test_direct_call_is_the_modules_call_to_the_bit_and_keeps_hooks():
    from imitrl.policies.heads import Chain, Squash
    from imitrl.policies.normalization import ObservationNormalizer

    torch.manual_seed(0)
    norm = ObservationNormalizer((3,))
    norm.fit(torch.randn(50, 3) * 4 + 1)
    net = Chain(norm, torch.nn.Linear(3, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2))
    x = torch.randn(7, 3)
    fast = direct_call(net)
    assert fast is not net and torch.equal(fast(x), net(x))
    seq = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.ReLU())
    assert torch.equal(direct_call(seq)(x), seq(x))
    # bound forwards (Squash's span, the normaliser's statistics, Tanh): the same bits,
    # at batch 1 and unbatched as a rollout calls them
    squash = Squash(torch.tensor([-2.0, 0.5]), torch.tensor([2.0, 3.0]))
    for module in (squash, norm, torch.nn.Tanh()):
        fast = direct_call(module)
        assert fast is not module
        for y in (torch.randn(64, module_width(module)), torch.randn(module_width(module))):
            assert torch.equal(fast(y), module(y))

    class Shifted(Squash):  # overrides forward alone: its own forward is called
        def forward(self, x):
            return super().forward(x) + 1

    shifted = Shifted(torch.tensor([-1.0]), torch.tensor([1.0]))
    assert torch.equal(direct_call(shifted)(x[:, :1]), shifted(x[:, :1]))
    bound = direct_call(norm)
    before = bound(x)
    norm.fit(torch.randn(50, 3))  # statistics refitted in place: the bound call sees them
    assert torch.equal(bound(x), norm(x)) and not torch.equal(bound(x), before)
    # a hook anywhere inside: the hooked module keeps its own call, so the hook runs
    calls = []
    net[2].register_forward_hook(lambda m, i, o: calls.append(1))
    assert torch.equal(direct_call(net)(x), net(x)) and len(calls) == 2
    # a global hook: nothing is bypassed
    handle = torch.nn.modules.module.register_module_forward_hook(lambda m, i, o: None)
    try:
        assert direct_call(net) is net
    finally:
        handle.remove()


@pytest.mark.parametrize("lanes", [1, 3])
def test_a_one_step_trajectory_keeps_its_time_dimension_on_both_paths(lanes):
    def make():
        return make_env("CartPole-v1", seed=5, num_envs=lanes, max_episode_steps=1)

    expert = cartpole_expert()

    def run(env):
        return rollout_episodes(env, expert, lanes)

    rows = run(make())
    assert rows.shape == (lanes,) and rows[keys.NEXT, keys.REWARD].shape == (lanes, 1)
    _rollouts_on_both_paths(make, run)


def test_an_evaluation_in_inference_mode_leaves_the_learner_trainable_and_stateful_modules_alone():
    env = make_env("Pendulum-v1", seed=3)
    learner = _learner(env)
    buffer = DemonstrationBuffer(action_spec=env.action_spec)
    buffer.extend(rollout_episodes(env, pendulum_expert(), 1))

    def returns():
        return episode_returns(env, learner.policy, 2, exploration=DET, seed=7).returns

    before = returns()
    fit_bc(learner, buffer, BCConfig(num_steps=3, batch_size=16))  # after the evaluation
    assert not any(p.is_inference() for p in learner.policy.parameters())
    assert not torch.equal(returns(), before)

    # an opaque module keeping a tensor it updates in place between calls keeps no_grad
    from tensordict.nn import TensorDictModuleBase

    class Counter(TensorDictModuleBase):
        in_keys, out_keys = [keys.OBSERVATION], [keys.ACTION]

        def __init__(self) -> None:
            super().__init__()
            self.count = None

        def forward(self, td):
            if self.count is None:
                self.count = torch.zeros(1)
            self.count += 1  # in place: refused on an inference tensor outside the mode
            return td.set(keys.ACTION, torch.zeros(1))

    counter = Counter()
    with set_exploration_type(DET):
        assert TensorPolicy(counter, env.batch_size).opaque
    n = episode_returns(env, counter, 1, exploration=DET).lengths.sum()
    assert not counter.count.is_inference()
    with torch.no_grad():
        counter(TensorDict({keys.OBSERVATION: torch.zeros(3)}))  # outside inference mode
    assert int(counter.count) == int(n) + 1

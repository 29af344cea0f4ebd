"""One builder: every learner ``--loss`` names is a loss-registry entry; ``default`` is a
name resolved for the env (``imitrl.learners.defaults``), recorded as resolved, and
checkpoints saved when ``default`` meant ``ActorCritic.for_env`` still load."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from torchrl.envs import GymWrapper

from imitrl.envs import make_env
from imitrl.jobs.bc import run_bc
from imitrl.jobs.checkpoint import CONFIG_FILE, WEIGHTS_FILE, load_learner
from imitrl.jobs.configs import BCJob, GAILJob
from imitrl.jobs.gail import run_gail
from imitrl.jobs.resolve import FOR_ENV, learner_factory, resolve_loss
from imitrl.learners import ActorCritic, TaskSpec, build, defaults, registry
from imitrl.learners.registry import LearnerConfig


def _rate(learner) -> float:
    return learner.opt_pi.param_groups[0]["lr"]


def _same_weights(a, b) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


@pytest.mark.parametrize(
    "env_id, plain, probabilistic",
    [("CartPole-v1", "cross_entropy", "cross_entropy"), ("Pendulum-v1", "mse", "gaussian_nll")],
)
def test_default_resolves_to_a_registry_entry_by_action_kind(env_id, plain, probabilistic):
    env = make_env(env_id, seed=0)
    assert resolve_loss("default", env) == plain
    assert resolve_loss("default", env, probabilistic=True) == probabilistic
    assert resolve_loss("l1" if plain == "mse" else plain, env) in registry.names()


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
def test_on_vector_observations_the_entry_is_the_network_default_built_before(env_id):
    # the learner --loss default built before (ActorCritic.for_env at 1e-3) and the
    # registry entry it resolves to now: the same weights from the same seed, same rate,
    # same loss, so runs recorded with "default" reproduce
    env = make_env(env_id, seed=0)
    for seed in (0, 3):
        old = build("for_env", env, hidden=(16, 8), lr=1e-3, seed=seed)
        new = learner_factory("default", env, hidden=(16, 8), lr=None, seed=seed)()
        assert _same_weights(old, new)
        assert (_rate(new), new.head, type(new.loss)) == (1e-3, old.head, type(old.loss))
        assert new.loss.loss_type == old.loss.loss_type


def test_on_integer_states_default_and_cross_entropy_build_the_same_table():
    env = make_env("FrozenLake-v1", seed=0)
    assert resolve_loss("default", env) == "cross_entropy"
    a = learner_factory("default", env, hidden=None, lr=None, seed=0)()
    b = learner_factory("cross_entropy", env, hidden=None, lr=None, seed=0)()
    assert _same_weights(a, b)
    assert sum(p.numel() for p in a.policy.parameters()) == 16 * 4  # a logits table
    assert _rate(a) == _rate(b) == defaults.TABLE_LR
    assert _rate(learner_factory("default", env, hidden=None, lr=0.02, seed=0)()) == 0.02


def test_default_learning_rates_are_one_per_network():
    table = TaskSpec(action=4, num_states=16)
    vector = TaskSpec(action=2, observation_dim=4)
    assert _rate(build("cross_entropy", table)) == defaults.TABLE_LR == 0.1
    assert _rate(build("cross_entropy", vector)) == defaults.NETWORK_LR == 1e-3
    assert _rate(build("cross_entropy", table, shared=dict(lr=0.3))) == 0.3
    assert LearnerConfig().lr is None  # unset: the network's own, resolved by build
    with pytest.raises(ValueError, match="must be positive"):
        build("cross_entropy", vector, shared=dict(lr=0.0))
    with pytest.raises(ValueError, match="actions must be one of"):
        defaults.default_loss("hybrid")


def test_a_table_at_its_default_rate_fits_its_demonstrations():
    # the reason for TABLE_LR: Adam moves a zero-initialised logit about lr a step, so at
    # the networks' 1e-3 a 1000-step fit leaves the table unsure of labels it never
    # contradicts; at 0.1 it is sure of them
    from tensordict import TensorDict

    from imitrl import keys
    from imitrl.algorithms import BCConfig, fit_bc

    g = torch.Generator().manual_seed(0)
    obs = torch.randint(0, 16, (200,), generator=g)
    label = obs % 4  # one action per state
    rows = TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, [200])
    sure = {}
    for lr in (None, 1e-3):
        learner = build("cross_entropy", TaskSpec(action=4, num_states=16), lr=lr)
        fit_bc(learner, rows, BCConfig(num_steps=1000, batch_size=64, seed=0))
        logits = learner.policy(rows.select(keys.OBSERVATION)).get(keys.LOGITS).detach()
        sure[lr] = float(torch.softmax(logits, -1).gather(-1, label[:, None]).mean())
    assert sure[None] > 0.99 and sure[1e-3] < 0.8, sure


class _MultiDiscreteEnv(gymnasium.Env):
    """A spec the registry does not describe (multi-discrete actions)."""

    observation_space = gymnasium.spaces.Box(-1.0, 1.0, (3,), np.float32)
    action_space = gymnasium.spaces.MultiDiscrete([2, 3])

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(3, np.float32), {}

    def step(self, action):
        return np.zeros(3, np.float32), 0.0, False, False, {}


def test_where_the_registry_builds_nothing_default_is_for_envs_network():
    with pytest.raises(ValueError, match=r"MultiOneHot actions .* categorical_action_encoding"):
        build("for_env", GymWrapper(_MultiDiscreteEnv()))
    env = GymWrapper(_MultiDiscreteEnv(), categorical_action_encoding=True)
    assert not TaskSpec.from_env(env).described  # multi-discrete: no registry entry but for_env
    with pytest.raises(ValueError, match="does not apply to this task"):
        build("cross_entropy", env)
    assert resolve_loss("default", env) == FOR_ENV
    learner = learner_factory("default", env, hidden=(8,), lr=None, seed=0)()
    assert _same_weights(learner, build("for_env", env, hidden=(8,), lr=1e-3, seed=0))
    with pytest.raises(ValueError, match="unknown loss 'tabel'; choose default or one of: cross"):
        learner_factory("tabel", env, hidden=(8,), lr=None, seed=0)


def test_a_run_records_the_resolved_name_and_reloads_from_it(tmp_path):
    config = BCJob(env="CartPole-v1", demos=1, num_steps=2, eval_episodes=1, out=tmp_path,
                   progress=False)  # fmt: skip
    results = run_bc(config)
    saved = json.loads((tmp_path / CONFIG_FILE).read_text())["config"]
    assert saved["loss"] == results["learner_loss"] == "cross_entropy"
    env = make_env("CartPole-v1", seed=0)
    assert isinstance(load_learner(tmp_path, env), ActorCritic)


def test_gail_records_the_probabilistic_default(tmp_path):
    config = GAILJob(env="Pendulum-v1", demos=1, total_steps=64, rollout_steps=64,
                     eval_episodes=1, eval_every=1, out=tmp_path, progress=False)  # fmt: skip
    results = run_gail(config)
    saved = json.loads((tmp_path / CONFIG_FILE).read_text())["config"]
    assert saved["loss"] == results["learner_loss"] == "gaussian_nll"


def test_a_checkpoint_saved_when_default_meant_for_env_still_loads(tmp_path):
    # what imitrl bc --loss default wrote on FrozenLake before: for_env's one-hot MLP,
    # recorded as "default"; it rebuilds as that network, not as today's table
    env = make_env("FrozenLake-v1", seed=0)
    old = build("for_env", env, hidden=(64, 64), lr=1e-3, seed=5)
    with torch.no_grad():
        for p in old.parameters():
            p.add_(0.25)  # trained weights, not the initialisation
    config = {**json.loads(json.dumps(_config_of(BCJob(env="FrozenLake-v1", seed=5)))),
              "loss": "default"}  # fmt: skip
    (tmp_path / CONFIG_FILE).write_text(json.dumps({"command": "bc", "config": config}))
    torch.save(old.state_dict(), tmp_path / WEIGHTS_FILE)
    loaded = load_learner(tmp_path, env)
    assert _same_weights(loaded, old)
    assert sum(p.numel() for p in loaded.policy.parameters()) > 16 * 4  # the MLP


def _config_of(job: BCJob) -> dict:
    from imitrl.jobs.checkpoint import to_json

    return to_json(job)


def test_hidden_is_refused_for_a_table_and_honoured_for_networks():
    lake = make_env("FrozenLake-v1", seed=0)
    with pytest.raises(ValueError, match=r"--hidden 32: on 16 integer states this entry builds a"):
        learner_factory("default", lake, hidden=(32,), lr=None, seed=0)
    mlp = learner_factory(FOR_ENV, lake, hidden=(32,), lr=None, seed=0)()
    assert [p.shape[0] for p in mlp.policy.parameters()][:2] == [32, 32]  # weight, bias
    cart = make_env("CartPole-v1", seed=0)
    default = learner_factory("default", cart, hidden=None, lr=None, seed=0)()
    assert _same_weights(default, build("for_env", cart, hidden=(64, 64), seed=0))
    narrow = learner_factory("default", cart, hidden=(8,), lr=None, seed=0)()
    assert sum(p.numel() for p in narrow.policy.parameters()) < 100
    assert BCJob().hidden is None and GAILJob().hidden is None


def test_a_table_checkpoint_that_recorded_the_old_hidden_default_loads(tmp_path):
    env = make_env("FrozenLake-v1", seed=0)
    table = learner_factory("cross_entropy", env, hidden=None, lr=None, seed=0)()
    with torch.no_grad():
        for p in table.parameters():
            p.add_(torch.arange(p.numel()).reshape(p.shape) / 10)
    config = {**_config_of(BCJob(env="FrozenLake-v1")), "loss": "cross_entropy",
              "hidden": [64, 64]}  # fmt: skip
    (tmp_path / CONFIG_FILE).write_text(json.dumps({"command": "bc", "config": config}))
    torch.save(table.state_dict(), tmp_path / WEIGHTS_FILE)
    assert _same_weights(load_learner(tmp_path, env), table)


class _PixelsOnlyEnv(gymnasium.Env):
    observation_space = gymnasium.spaces.Dict(
        {"pixels": gymnasium.spaces.Box(0, 255, (16, 16, 3), np.uint8)}
    )
    action_space = gymnasium.spaces.Discrete(3)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return {"pixels": np.zeros((16, 16, 3), np.uint8)}, {}

    def step(self, action):
        return {"pixels": np.zeros((16, 16, 3), np.uint8)}, 0.0, False, False, {}


def test_on_images_default_is_for_envs_cnn_with_or_without_a_state():
    from imitrl.envs.pixel_tasks import PixelBalanceEnv

    beside = make_env("Pendulum-v1", seed=0, pixels=(16, 16))  # pixels and a state
    balance = PixelBalanceEnv(pixels=(16, 16), seed=0)
    alone = GymWrapper(_PixelsOnlyEnv())  # no "observation" at all
    for env in (beside, balance, alone):
        assert resolve_loss("default", env) == FOR_ENV
        assert resolve_loss("default", env, probabilistic=True) == FOR_ENV
        learner = learner_factory("default", env, hidden=None, lr=None, seed=0)()
        assert learner.pixel_inputs is not None  # a CNN that reads the image
        assert _same_weights(learner, build("for_env", env, seed=0))
    assert not TaskSpec.from_env(alone).described  # images alone: for_env's CNN
    with pytest.raises(ValueError, match="does not apply to this task"):
        build("mse", alone)


def test_gail_refuses_an_integer_state_learner_saying_what_to_do():
    from imitrl.algorithms.adversarial import GAILConfig, gail
    from imitrl.data import DemonstrationBuffer

    env = make_env("FrozenLake-v1", seed=0)
    for learner in (
        learner_factory("default", env, hidden=None, lr=None, seed=0)(),  # a table
        learner_factory(FOR_ENV, env, hidden=None, lr=None, seed=0)(),  # a one-hot MLP
    ):
        with pytest.raises(ValueError, match=r"reads 16 integer states .* one-hot the env"):
            gail(env, learner, DemonstrationBuffer(num_states=16), GAILConfig())


@pytest.mark.parametrize(
    "env_id, kwargs",
    [
        ("FrozenLake-v1", ()),
        ("CartPole-v1", ()),
        ("Pendulum-v1", ()),
        ("metaworld/reach-v3", (("obs_type", "pixels_agent_pos"), ("width", 32), ("height", 32))),
    ],
    ids=["frozenlake", "cartpole", "pendulum", "pixels"],
)
def test_the_clis_default_learner_is_builds_default_bit_for_bit(tmp_path, env_id, kwargs):
    """What ``imitrl bc --env ...`` trains (its preparation, flags as given) and
    ``build("default", env)``: the same entry, the same parameters to the bit."""
    from imitrl.jobs.bc import prepare

    if env_id.startswith("metaworld"):
        pytest.importorskip("metaworld")
    config = BCJob(env=env_id, env_kwargs=kwargs, expert=None, dataset=Path("org/name"),
                   out=tmp_path / "out", progress=False, seed=7)  # fmt: skip
    setup = prepare(config, "bc", tmp_path / "run")
    try:
        cli = setup.make_learner()
        mine = build("default", setup.env, seed=7)
        assert setup.loss == ("for_env" if env_id.startswith("metaworld") else setup.loss)
        assert type(cli) is type(mine)
        cli_state, my_state = cli.state_dict(), mine.state_dict()
        assert cli_state.keys() == my_state.keys()
        for key in cli_state:
            assert torch.equal(cli_state[key], my_state[key]), key
        assert cli.opt_pi.param_groups[0]["lr"] == mine.opt_pi.param_groups[0]["lr"]
    finally:
        setup.close()


@pytest.mark.parametrize("env", [None, "CartPole-v1", 3])
def test_build_without_an_env_or_a_task_says_what_it_needs(env):
    """A hostile review: ``build("default", None)`` and a plain gymnasium env raised a bare
    AttributeError."""
    with pytest.raises(ValueError, match=r"build needs a TorchRL env .* or a TaskSpec, got"):
        build("default", env)


def test_build_refuses_a_plain_gymnasium_env():
    import gymnasium

    with pytest.raises(ValueError, match=r"got TimeLimit"):
        build("default", gymnasium.make("CartPole-v1"))

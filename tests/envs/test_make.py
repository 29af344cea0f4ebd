"""``make_env``'s refusals: a mistyped id is named with ids that can be made."""

from __future__ import annotations

import re

import pytest

from imitrl.envs import make_env


def test_a_mistyped_id_suggests_only_envs_that_need_no_jax():
    """A hostile review: ``CliffWalking-v0`` suggested ``tabular/CliffWalking-v0``, which
    then failed with "No module named 'jax'"."""
    with pytest.raises(ValueError, match=r"unknown gymnasium env id 'CliffWalking-v0'") as err:
        make_env("CliffWalking-v0", seed=0)
    said = str(err.value)
    assert "CliffWalking-v1" in said and "tabular/" not in said and "phys2d/" not in said


@pytest.mark.parametrize(
    ("env_id", "kwargs", "said"),
    [
        ("Pendulum-v1", {"g": "abc"}, "g='abc': Pendulum-v1's g defaults to 10.0 (float)"),
        ("Pendulum-v1", {"g": True}, "g=True: Pendulum-v1's g defaults to 10.0 (float)"),
        ("FrozenLake-v1", {"is_slippery": "false"}, "defaults to True (bool); give a bool"),
        ("FrozenLake-v1", {"map_name": 8}, "map_name defaults to '4x4' (str)"),
    ],
)
def test_an_argument_of_another_kind_than_its_default_is_refused(env_id, kwargs, said):
    """A review: ``--env-kwarg g=abc`` failed inside Pendulum's first step, a traceback."""
    with pytest.raises(ValueError, match=re.escape(said)):
        make_env(env_id, seed=0, env_kwargs=kwargs)


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [
        ("Pendulum-v1", {"g": 9}),
        ("Pendulum-v1", {"g": 9.81}),
        ("FrozenLake-v1", {"is_slippery": False, "map_name": "8x8"}),
        ("FrozenLake-v1", {"desc": ["SF", "HG"]}),  # default None: taken as given
    ],
)
def test_arguments_of_their_defaults_kind_are_taken(env_id, kwargs):
    make_env(env_id, seed=0, env_kwargs=kwargs).close()


def test_plain_gym_is_what_make_env_built_unchanged_and_nothing_else():
    import gymnasium
    from torchrl.envs import GymEnv, StepCounter

    from imitrl.envs.make import plain_gym

    one = make_env("Pendulum-v1", seed=0)
    plain = plain_gym(one)
    assert plain is not None and plain.base is one
    assert isinstance(plain.inner, gymnasium.Env) and plain.inner.spec.id == "Pendulum-v1"
    lanes = plain_gym(make_env("CartPole-v1", seed=0, num_envs=3))
    assert lanes is not None and isinstance(lanes.inner, gymnasium.vector.SyncVectorEnv)
    assert plain_gym(make_env("CartPole-v1", seed=0).append_transform(StepCounter())) is None
    assert plain_gym(make_env("CartPole-v1", seed=0, frame_skip=2)) is None
    assert plain_gym(GymEnv("CartPole-v1")) is None  # not built by make_env
    pytest.importorskip("mujoco")
    doubled = make_env("InvertedPendulum-v5", seed=0)  # float64 observations: DoubleToFloat
    inside = plain_gym(doubled)
    assert inside is not None and inside.base is doubled.base_env
    assert plain_gym(doubled.append_transform(StepCounter())) is None


def test_a_metaworld_ids_task_cannot_be_swapped_by_an_argument():
    """A hostile review: task=push-v3 on metaworld/reach-v3 built the push env, and reach's
    expert labelled it."""
    pytest.importorskip("metaworld")
    with pytest.raises(ValueError, match=r"metaworld/reach-v3 names its task; give --env "
                                         r"metaworld/push-v3"):  # fmt: skip
        make_env("metaworld/reach-v3", seed=0, env_kwargs={"task": "push-v3"})


@pytest.mark.parametrize(
    ("kwargs", "said"),
    [
        ({"map_name": "16x16"}, "refused --env-kwarg map_name='16x16': KeyError: '16x16'"),
        ({"desc": "SFFG"}, "refused --env-kwarg desc='SFFG': ValueError: not enough values"),
        ({"reward_schedule": (1, 0)}, "refused --env-kwarg reward_schedule=(1, 0): IndexError"),
    ],
)
def test_a_value_the_constructor_cannot_use_is_one_bounded_line(kwargs, said):
    """A hostile review: these were tracebacks, or a line naming neither the flag nor the
    value; an argument 100,000 items long gave a 1.4 MB line."""
    with pytest.raises(ValueError) as err:
        make_env("FrozenLake-v1", seed=0, env_kwargs=kwargs)
    assert said in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ValueError) as err:
        make_env("FrozenLake-v1", seed=0, env_kwargs={"map_name": "8x8" * 50_000})
    assert len(str(err.value)) < 700

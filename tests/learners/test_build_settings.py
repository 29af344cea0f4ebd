"""``build``'s shared settings are checked for their kind (a hostile review: ``hidden="64"``
built widths 6 and 4, ``(2.7,)`` a width of 2, ``lr=inf`` NaN losses without an error,
``seed=1.5`` seed 1), and the registry keeps ``default`` and padded names out."""

from __future__ import annotations

import math
import warnings

import pytest

from imitrl.envs import make_env
from imitrl.learners import build, registry


@pytest.fixture(scope="module")
def pendulum():
    return make_env("Pendulum-v1", seed=0)


@pytest.mark.parametrize(
    "setting, said",
    [
        ({"hidden": "64"}, "hidden must be a list of layer widths"),
        ({"hidden": (2.7,)}, "hidden must be a list of layer widths"),
        ({"hidden": (0,)}, "hidden must be a list of layer widths"),
        ({"hidden": (True,)}, "hidden must be a list of layer widths"),
        ({"hidden": 64}, "hidden must be a list of layer widths"),
        ({"lr": math.inf}, "lr must be a positive finite number"),
        ({"lr": True}, "lr must be a positive finite number"),
        ({"lr": "1e-3"}, "lr must be a positive finite number"),
        ({"seed": 1.5}, r"seed must be an integer in \[0, 2_147_483_647\], got 1\.5"),
        ({"seed": "3"}, "seed must be an integer"),
        ({"seed": True}, "seed must be an integer"),
        ({"seed": -1}, "seed must be an integer"),
        ({"normalize": "no"}, r"normalize must be True or False, got 'no'"),
        ({"normalize": 0}, "normalize must be True or False"),
        ({"value": "yes"}, "value must be True or False"),
        ({"device": 0}, "device must be a string"),
        ({"device": ["cpu"]}, "device must be a string"),
        ({"options": 3}, "loss mse's options must be none .it has no options., got int"),
    ],
)
def test_a_setting_of_the_wrong_kind_is_refused_naming_it(pendulum, setting, said):
    with pytest.raises(ValueError, match=said):
        build("mse", pendulum, **setting)


def test_options_of_another_entry_are_refused_naming_the_type(pendulum):
    """A fourth hostile review: ``options=3`` was an AttributeError inside the builder."""
    from imitrl.learners.catalogue import ForEnvOptions

    with pytest.raises(ValueError, match="options must be UnetDiffusionConfig, got ForEnvOptions"):
        build("diffusion_unet", pendulum, options=ForEnvOptions())
    with pytest.raises(ValueError, match="options must be ForEnvOptions, got int"):
        build("for_env", pendulum, options=3)


def test_settings_of_their_kind_build_the_same_network_as_before(pendulum):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = build("mse", pendulum, hidden=[16, 16], lr=1e-3, seed=3)
        b = build("mse", pendulum, hidden=(16, 16), lr=1e-3, seed=3)
    assert all((x == y).all() for x, y in zip(a.parameters(), b.parameters(), strict=True))


@pytest.mark.parametrize("name", ["default", "bad name ", " x", ""])
def test_default_and_names_with_spaces_cannot_be_registered(name):
    with pytest.raises(ValueError, match=r"default|without spaces"):
        registry.register(name, actions="continuous", summary="mine")(lambda task, cfg: None)
    assert name not in registry.names()

"""``make_env``'s refusals: a mistyped id is named with ids that can be made."""

from __future__ import annotations

import pytest

from imitrl.envs import make_env


def test_a_mistyped_id_suggests_only_envs_that_need_no_jax():
    """A hostile review: ``CliffWalking-v0`` suggested ``tabular/CliffWalking-v0``, which
    then failed with "No module named 'jax'"."""
    with pytest.raises(ValueError, match=r"unknown gymnasium env id 'CliffWalking-v0'") as err:
        make_env("CliffWalking-v0", seed=0)
    said = str(err.value)
    assert "CliffWalking-v1" in said and "tabular/" not in said and "phys2d/" not in said

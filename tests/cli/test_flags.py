"""``--env-kwarg name=value``: the value as it reads (a hostile review: ``is_slippery=false``
was the string ``'false'``, which is true, and FrozenLake stayed slippery)."""

from __future__ import annotations

import argparse

import pytest

from imitrl.cli.flags import _name_value


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("is_slippery=false", False),
        ("is_slippery=true", True),
        ("render_mode=none", None),
        ("render_mode=null", None),
        ("is_slippery=False", False),
        ("map_name=8x8", "8x8"),
        ("map_name='false'", "false"),
        ("g=9.81", 9.81),
        ("size=(4, 4)", (4, 4)),
        ("desc=['SF', 'HG']", ["SF", "HG"]),
        ("obs_type=pixels_agent_pos", "pixels_agent_pos"),
        ("empty=", ""),
    ],
)
def test_a_value_reads_as_it_is_spelled(text, value):
    name, got = _name_value(text)
    assert name == text.split("=", 1)[0] and got == value and type(got) is type(value)


@pytest.mark.parametrize("text", ["false", "=1", "1x=2", "a b=3"])
def test_a_pair_without_a_keyword_name_is_refused(text):
    with pytest.raises(argparse.ArgumentTypeError, match="expected name=value"):
        _name_value(text)


def test_a_lake_made_with_is_slippery_false_is_not_slippery():
    import gymnasium

    lake = gymnasium.make("FrozenLake-v1", **dict([_name_value("is_slippery=false")]))
    assert len(lake.unwrapped.P[0][0]) == 1  # one outcome per action: not slippery
    assert len(gymnasium.make("FrozenLake-v1").unwrapped.P[0][0]) == 3


@pytest.mark.parametrize("text", ["64,,64", "64,", ",64"])
def test_a_value_left_out_between_commas_is_refused(text, capsys):
    """A review: ``--discriminator-hidden 64,,64`` was read as (64, 64), silently."""
    from imitrl.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["gail", "--discriminator-hidden", text, "--out", "never"])
    assert stop.value.code == 2
    assert "an empty value between commas" in capsys.readouterr().err

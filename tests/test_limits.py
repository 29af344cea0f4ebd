"""``imitrl.limits.Bound``: what ``--help`` says a flag takes is what its check takes (a
review: ``compare --alpha`` said ``(0, 1]`` and refused 1)."""

from __future__ import annotations

import pytest

from imitrl.limits import Bound


@pytest.mark.parametrize(
    ("bound", "said", "taken", "refused"),
    [
        (Bound(0, 1, integer=False, low_open=True, high_open=True), "in (0, 1)", [0.5, 1e-9],
         [0, 1, 1.5]),
        (Bound(0, 1, integer=False, low_open=True), "in (0, 1]", [1, 0.5], [0, 1.01]),
        (Bound(0, 1, integer=False), "in [0, 1]", [0, 1], [-0.1, 1.1]),
    ],
)  # fmt: skip
def test_the_range_said_is_the_range_checked(bound, said, taken, refused):
    assert bound.describe() == said
    assert all(bound.holds(v) for v in taken)
    for value in refused:
        assert not bound.holds(value)
        with pytest.raises(ValueError, match=rf"--x must be {__import__('re').escape(said)}"):
            bound.check(value, "--x")


def test_a_required_flag_is_named_when_missing_and_in_its_help(capsys):
    from imitrl.cli import main

    with pytest.raises(SystemExit) as stop:  # argparse's exit: status 2, one line
        main(["compare", "--b", "expert", "--env", "CartPole-v1"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "the following arguments are required: --a" in err and "Traceback" not in err
    with pytest.raises(SystemExit):
        main(["compare", "--help"])
    shown = capsys.readouterr().out
    assert "(required)" in shown and "MISSING" not in shown and "must be in [1e-12, 1)" in shown

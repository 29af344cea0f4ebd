"""The row contract's bounds (:mod:`imitrl.data.validation`): a round number is one a
DAgger run could have collected."""

from __future__ import annotations

import pytest
import torch

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.limits import MAX_ROUNDS
from tests.datasets.test_datasets_faults import _rows


@pytest.mark.parametrize("disk", [False, True])
def test_a_round_past_the_most_rounds_is_refused_and_nothing_is_added(tmp_path, disk):
    rows = _rows(0)
    rows.set(keys.ROUND, torch.full_like(rows.get(keys.ROUND), 2**63 - 1))
    buffer = DemonstrationBuffer(path=tmp_path / "b" if disk else None)
    with pytest.raises(ValueError, match=rf"'round' must be at most {MAX_ROUNDS}"):
        buffer.extend(rows)
    assert len(buffer) == 0
    rows.set(keys.ROUND, torch.full_like(rows.get(keys.ROUND), MAX_ROUNDS))
    buffer.extend(rows)
    assert max(buffer.rounds()) == MAX_ROUNDS


@pytest.mark.parametrize("disk", [False, True])
def test_an_episode_id_leaving_no_id_after_it_is_refused_and_sample_0_is_one_line(tmp_path, disk):
    """A hostile review: id 2**63 - 1 was taken, and a disk buffer holding it never resumed
    (its next id past what the layout records); ``sample(0)`` divided by zero in memory."""
    from tests.data.test_disk import cartpole_rows

    buf = DemonstrationBuffer(path=tmp_path / "b" if disk else None)
    with pytest.raises(ValueError, match="leaves no id after it"):
        buf.extend(cartpole_rows(3, first_episode=2**63 - 1))
    assert len(buf) == 0
    buf.extend(cartpole_rows(3, first_episode=2**63 - 2))  # the largest id there is
    with pytest.raises(ValueError, match="sample needs a positive batch_size, got 0"):
        buf.sample(0)
    if disk:
        del buf
        assert len(DemonstrationBuffer(path=tmp_path / "b", resume=True)) == 3


def test_text_entries_are_refused_not_stored_half():
    """A hostile review: a 'task' string was filled into later rows that had none and lost
    on save and resume."""
    from tests.data.test_disk import cartpole_rows

    rows = cartpole_rows(3)
    rows.set_non_tensor("task", "pick")
    with pytest.raises(ValueError, match=r"rows hold non-tensor entries \['task'\]"):
        DemonstrationBuffer().extend(rows)


@pytest.mark.parametrize("disk", [False, True])
def test_a_dotted_key_part_is_refused_as_it_would_share_a_nested_keys_column(tmp_path, disk):
    """A hostile review: ``"x.y"`` and ``("x", "y")`` had one schema name, one column file."""
    rows = _rows(0)
    rows.set(("extra", "y"), torch.zeros(rows.shape[0]))
    rows.set("extra.y", torch.ones(rows.shape[0]))
    buffer = DemonstrationBuffer(path=tmp_path / "b" if disk else None)
    with pytest.raises(
        ValueError, match=r"'extra.y': a key part may not contain '.'.*\('extra', 'y'\)"
    ):
        buffer.extend(rows)
    assert len(buffer) == 0
    del rows["extra.y"]
    buffer.extend(rows)
    assert (buffer.data.get(("extra", "y")) == 0).all()


@pytest.mark.parametrize("disk", [False, True])
def test_complex_values_are_refused_naming_the_key(tmp_path, disk):
    """A hostile review: a complex NaN passed the finiteness check (real dtypes only)."""
    rows = _rows(0)
    obs = rows.get(keys.OBSERVATION).to(torch.complex64)
    obs[0, 0] = complex(float("nan"), 0.0)
    rows.set(keys.OBSERVATION, obs)
    buffer = DemonstrationBuffer(path=tmp_path / "b" if disk else None)
    with pytest.raises(ValueError, match="rows hold complex values under 'observation'"):
        buffer.extend(rows)
    assert len(buffer) == 0

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
def test_a_dotted_key_beside_its_nested_twin_is_refused_and_alone_is_kept(tmp_path, disk):
    """A hostile review: ``"x.y"`` and ``("x", "y")`` had one schema entry, so the checks
    of one were the other's; a dotted key alone (a Minari Dict's ``"pos.x"``) is data."""
    rows = _rows(0)
    rows.set(("extra", "y"), torch.zeros(rows.shape[0]))
    rows.set("extra.y", torch.ones(rows.shape[0]))
    buffer = DemonstrationBuffer(path=tmp_path / "b" if disk else None)
    with pytest.raises(ValueError, match=r"row keys .* both read 'extra.y'"):
        buffer.extend(rows)
    assert len(buffer) == 0
    del rows["extra"]
    buffer.extend(rows)
    assert (buffer.data.get("extra.y") == 1).all() and "extra" not in buffer.data.keys()
    if disk:  # resumed under the same key
        del buffer
        again = DemonstrationBuffer(path=tmp_path / "b", resume=True)
        assert (again.data.get("extra.y") == 1).all()


@pytest.mark.parametrize("disk", [False, True])
def test_complex_values_are_refused_naming_the_key(tmp_path, disk):
    """A hostile review: a complex NaN passed the finiteness check (real dtypes only)."""
    rows = _rows(0)
    obs = rows.get(keys.OBSERVATION).to(torch.complex64)
    obs[0, 0] = complex(float("nan"), 0.0)
    rows.set(keys.OBSERVATION, obs)
    buffer = DemonstrationBuffer(path=tmp_path / "b" if disk else None)
    with pytest.raises(ValueError, match=r"rows hold torch\.complex64 values under 'observation'"):
        buffer.extend(rows)
    assert len(buffer) == 0


@pytest.mark.parametrize("dtype", [torch.uint16, torch.uint32, torch.uint64, torch.float8_e4m3fn])
@pytest.mark.parametrize("disk", [False, True])
def test_a_dtype_the_buffer_cannot_store_is_refused_naming_the_cast(tmp_path, disk, dtype):
    """A hostile review: a Minari uint16 depth image raised ``index_put not implemented
    for 'UInt16'`` from torch, float8 ``aminmax_cpu``, on the way into a buffer."""
    rows = _rows(0)
    rows.set("depth", torch.ones(rows.shape[0], 2).to(dtype))
    buffer = DemonstrationBuffer(path=tmp_path / "b" if disk else None)
    with pytest.raises(ValueError, match=f"rows hold {dtype} values under 'depth'.*cast it"):
        buffer.extend(rows)
    assert len(buffer) == 0
    rows.set("depth", rows.get("depth").to(torch.float32).to(torch.int32))  # the cast it names
    buffer.extend(rows)
    assert (buffer.data.get("depth") == 1).all()

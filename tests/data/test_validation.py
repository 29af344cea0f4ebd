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

"""``exact_cast``: a dataset's values in their declared dtype only when none changes."""

from __future__ import annotations

import numpy as np
import pytest

from imitrl.datasets._common import exact_cast


@pytest.mark.parametrize(
    ("values", "dtype", "bad"),
    [
        (np.array([3, 2**64 - 1], dtype=np.uint64), "int64", 2**64 - 1),
        (np.array([2**32 - 1], dtype=np.uint32), "int32", 2**32 - 1),
        (np.array([2**16 - 1], dtype=np.uint16), "int16", 2**16 - 1),
        (np.array([0, -1], dtype=np.int64), "uint64", -1),
        (np.array([300], dtype=np.int64), "int8", 300),
        (np.array([0.5]), "int64", None),
    ],
)
def test_a_cast_that_changes_a_value_is_refused(values, dtype, bad):
    """A hostile review: uint64 ``2**64 - 1`` declared int64 loaded as -1 (the cast back
    gives the bits back, so the check passed)."""
    match = "refusing to truncate" if bad is None else f"value {bad} does not fit"
    with pytest.raises(ValueError, match=match):
        exact_cast(values, dtype, where="x.parquet: action")


@pytest.mark.parametrize(
    ("values", "dtype"),
    [
        (np.array([0, 2**63 - 1], dtype=np.uint64), "int64"),
        (np.array([-3, 4], dtype=np.int64), "int8"),
        (np.array([0, 1], dtype=np.int64), "bool"),
        (np.array([7], dtype=np.uint8), "int64"),
        (np.array([1.5, np.nan]), "float32"),
    ],
)
def test_a_cast_that_keeps_every_value_is_made(values, dtype):
    cast = exact_cast(values, dtype, where="x")
    assert cast.dtype == np.dtype(dtype)
    assert np.array_equal(cast.astype(np.float64), values.astype(np.float64), equal_nan=True)

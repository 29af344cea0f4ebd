"""Datasets meeting envs and each other: exact dtype casts, Minari rows through LeRobot files."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from imitrl import keys
from imitrl.datasets import load_lerobot, load_minari, save_lerobot
from imitrl.datasets._common import _fit
from tests.datasets.minari.test_minari import _write


@pytest.mark.parametrize(
    ("values", "dtype"),
    [
        (torch.tensor([-1, 20, 2**24]), torch.float32),  # Taxi's int64 rewards
        (torch.tensor([2**53]), torch.float64),
        (torch.tensor([0, 255], dtype=torch.uint8), torch.float16),
        (torch.tensor([True, False]), torch.float32),
        (torch.tensor([1.5, -2.25], dtype=torch.float64), torch.float32),
        (torch.tensor([7, -7], dtype=torch.int64), torch.int32),
    ],
)
def test_casts_that_keep_every_value(values, dtype):
    notes: list[str] = []
    out = _fit(values[:, None], torch.Size([1]), dtype, "'x'", "file", notes)
    assert out.dtype == dtype and out.shape == (len(values), 1)
    assert torch.equal(out.squeeze(-1).double(), values.double())
    assert len(notes) == 1 and f"-> {dtype}" in notes[0]


@pytest.mark.parametrize(
    ("values", "dtype", "message"),
    [
        (torch.tensor([2**24 + 1]), torch.float32, "holds 16777217"),
        (torch.tensor([2**63 - 1]), torch.float32, "holds 9223372036854775807"),
        (torch.tensor([70000], dtype=torch.int32), torch.float16, "holds 70000"),
        (torch.tensor([2**40]), torch.int32, "holds 1099511627776"),
        (torch.tensor([1e300], dtype=torch.float64), torch.float32, "holds 1e\\+300"),
        (torch.tensor([0.5]), torch.int64, "refusing to convert floating"),
        (torch.tensor([1.0]), torch.bool, "refusing to convert floating"),
        (torch.tensor([1, 0]), torch.bool, "between integers and booleans"),
    ],
)
def test_casts_that_would_change_values_are_refused(values, dtype, message):
    with pytest.raises(ValueError, match=rf"^file: 'x' .*{message}"):
        _fit(values[:, None], torch.Size([1]), dtype, "'x'", "file", [])


def test_minari_dict_observations_round_trip_through_lerobot(tmp_path):
    box = {"type": "Box", "dtype": "float64", "shape": [2], "low": [-9.0] * 2, "high": [9.0] * 2}
    space = {
        "type": "Dict",
        "subspaces": {
            "achieved_goal": box,
            "extra": {"type": "Dict", "subspaces": {"mode": {"type": "Discrete", "n": 3}}},
        },
    }
    rng = np.random.default_rng(0)
    episodes = [
        {
            "observations": {
                "achieved_goal": rng.standard_normal((n + 1, 2)),
                "extra": {"mode": rng.integers(0, 3, n + 1)},
            },
            "actions": rng.integers(0, 2, n),
            "rewards": rng.random(n),
            "terminations": np.arange(n) == n - 1,
            "truncations": np.zeros(n, dtype=bool),
        }
        for n in (4, 2)
    ]
    rows = load_minari(_write(tmp_path / "minari", episodes, obs_space=space)).rows
    root = save_lerobot(rows, tmp_path / "lerobot", fps=10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = load_lerobot(root).rows
    assert set(back.keys(True, True)) == set(rows.keys(True, True))
    for key in rows.keys(True, True):
        x, y = rows.get(key), back.get(key)
        assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y), key
    assert back[keys.OBSERVATION, "extra", "mode"].shape == (6,)

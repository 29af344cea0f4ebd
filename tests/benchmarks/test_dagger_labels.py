"""benchmarks/dagger_labels.py's probe: which rows are near the object and which of their
labels are retreats (lift with the gripper open), counted per round."""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

from dagger_labels import NEAR_XY, NEAR_Z, RETREAT_Z, label_phases  # noqa: E402
from imitrl import keys  # noqa: E402


def _row(hand_xy: float, hand_dz: float, z: float, grip: float) -> tuple[list, list]:
    obs = [0.0] * 39
    obs[0], obs[2] = hand_xy, 0.1 + hand_dz  # hand; the object at (0, 0, 0.1)
    obs[6] = 0.1
    return obs, [0.0, 0.0, z, grip]


def test_rows_near_the_object_and_retreats_are_counted_per_round():
    rows = [
        (0, _row(0.0, 0.0, -1.0, 0.6)),                  # near, descends, grasps: round 0
        (1, _row(NEAR_XY / 2, 0.02, 1.0, -1.0)),          # near, lifts open: a retreat
        (1, _row(NEAR_XY / 2, 0.02, 1.0, 0.6)),           # near, lifts closed: carries it
        (1, _row(NEAR_XY / 2, 0.02, RETREAT_Z, -1.0)),    # z at the threshold: not above it
        (1, _row(2 * NEAR_XY, 0.0, 1.0, -1.0)),           # lifts open far away: not near
        (2, _row(0.0, NEAR_Z + 0.01, 1.0, 0.0)),          # too high above it: not near
        (2, _row(0.0, NEAR_Z - 0.01, 1.0, 0.0)),          # near, grip 0 counts as open
    ]  # fmt: skip
    td = TensorDict(
        {
            keys.OBSERVATION: torch.tensor([o for _, (o, _) in rows]),
            keys.EXPERT_ACTION: torch.tensor([a for _, (_, a) in rows]),
            keys.ROUND: torch.tensor([r for r, _ in rows]),
        },
        batch_size=[len(rows)],
    )
    assert label_phases(td) == {
        "0": {"rows": 1, "near": 1, "retreats": 0},
        "1": {"rows": 4, "near": 3, "retreats": 1},
        "2": {"rows": 2, "near": 1, "retreats": 1},
    }


def test_a_quick_runs_block_says_it_is_a_smoke_run_and_a_full_ones_is_as_committed():
    """A review: a --quick block's header named the full run's command, MT10 and 5 seeds."""
    import json

    from dagger_labels import markdown

    payload = json.loads((ROOT / "benchmarks" / "results" / "dagger_labels.json").read_text())
    args = (payload["runs"], payload["wall_seconds"], tuple(payload["load_average"]))
    full = markdown(*args)
    assert full.startswith("`python benchmarks/dagger_labels.py --jobs 2`")
    assert full in (ROOT / "benchmarks" / "README.md").read_text()
    smoke = markdown(*args, quick=True)
    assert smoke.startswith("Smoke run (`--quick`: 10 task(s), 1 seed, 4 schedules")
    assert smoke.endswith(full.split("\n\n", 1)[1])

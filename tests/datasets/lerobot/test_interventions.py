"""What a LeRobot dataset's DAgger columns must hold on load (issue 48).

A dataset as LeRobot's DAgger strategy records it (``intervention`` bool ``(1,)``, ``action``
the executed action, no imitrl column) loads with ``EXPERT_EXECUTED`` from ``intervention``;
other tools' int64 or float32 0/1 columns load as booleans. Refused, naming the file, the
episode and the frame: an ``intervention`` value that is not a boolean, an intervention frame
without its corrected action (null, NaN, or no action feature at all), rounds out of order or
changing inside an episode; a streamed load refused at a later round adds nothing of the
earlier ones to the buffer.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, save_dagger_lerobot, save_lerobot
from tests.datasets.lerobot.test_dagger import dagger_rows

DATA = "data/chunk-000/file-000.parquet"
LENGTH = 6


def _load(root, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_lerobot(root, **kwargs)


def lerobot_recording(tmp_path: Path, features=("observation.state", "action", "intervention")):
    """As LeRobot's DAgger strategy (record_autonomous=True) writes one: ``action`` is what
    was executed (the human's on a correction), ``intervention`` tags the corrections."""
    rows = dagger_rows(rounds=(0, 0, 0, 0, 0), length=LENGTH)
    executed = rows[keys.EXPERT_EXECUTED]
    executed[:] = torch.tensor([False, True, True, False, False, True] * 5)
    rows.set(keys.EXPERT_ACTION, rows[keys.ACTION])
    root = save_lerobot(rows, tmp_path / "rec", fps=10, features=list(features))
    (root / "meta/imitrl.json").unlink()  # LeRobot writes none: read as LeRobot's own
    return root, rows


def _replace_column(root: Path, name: str, array: pa.Array, dtype: str | None = None) -> None:
    table = pq.read_table(root / DATA)
    table = table.set_column(table.column_names.index(name), name, array)
    pq.write_table(table, root / DATA)
    if dtype is not None:
        info = json.loads((root / "meta/info.json").read_text())
        info["features"][name]["dtype"] = dtype
        (root / "meta/info.json").write_text(json.dumps(info))


def _foreign(rows, tmp_path):
    """imitrl's rows as a dataset another tool edited (no meta/imitrl.json checksums)."""
    root = save_dagger_lerobot(rows, tmp_path / "ds", fps=10)
    (root / "meta/imitrl.json").unlink()
    return root


def test_a_recording_of_lerobots_dagger_strategy_loads_its_interventions(tmp_path):
    root, rows = lerobot_recording(tmp_path)
    loaded = _load(root)
    assert loaded.loaded["intervention"] == keys.EXPERT_EXECUTED
    assert torch.equal(loaded.rows[keys.EXPERT_EXECUTED], rows[keys.EXPERT_EXECUTED])
    assert torch.equal(loaded.rows[keys.EXPERT_ACTION], rows[keys.ACTION])
    assert loaded.rows[keys.ROUND].eq(0).all()


@pytest.mark.parametrize("dtype", ["int64", "float32"])
def test_other_tools_zero_one_columns_load_as_booleans(tmp_path, dtype):
    root, rows = lerobot_recording(tmp_path)
    flags = rows[keys.EXPERT_EXECUTED].numpy().astype(dtype)
    _replace_column(root, "intervention", pa.array(flags), dtype)
    got = _load(root).rows[keys.EXPERT_EXECUTED]
    assert got.dtype == torch.bool and torch.equal(got, rows[keys.EXPERT_EXECUTED])


@pytest.mark.parametrize("dtype, bad", [("int64", 2), ("float32", 0.5), ("int64", -1)])
@pytest.mark.parametrize("stream", [False, True])
def test_an_intervention_that_is_not_boolean_is_refused_naming_episode_and_frame(
    tmp_path, dtype, bad, stream
):
    root, rows = lerobot_recording(tmp_path)
    flags = rows[keys.EXPERT_EXECUTED].numpy().astype(dtype)
    flags[3 * LENGTH + 4] = bad
    _replace_column(root, "intervention", pa.array(flags), dtype)
    buffer = DemonstrationBuffer()
    with pytest.raises(
        ValueError, match=rf"file-000\.parquet: episode 3, frame 4: 'intervention' holds \[{bad}"
    ):
        _load(root, into=buffer) if stream else _load(root)
    assert len(buffer) == 0


@pytest.mark.parametrize("value, said", [(np.nan, "nan"), (None, "null")])
@pytest.mark.parametrize("stream", [False, True])
def test_an_intervention_frame_without_its_corrected_action_is_refused(
    tmp_path, value, said, stream
):
    root, rows = lerobot_recording(tmp_path)
    actions = rows[keys.ACTION].numpy().tolist()
    actions[2 * LENGTH + 2][1] = value  # episode 2, frame 2: a correction
    _replace_column(root, "action", pa.array(actions, pa.list_(pa.float32(), 2)))
    buffer = DemonstrationBuffer()
    with pytest.raises(
        ValueError,
        match=rf"feature 'action'.*{said}.* \(episode 2, frame 2: an intervention frame, which "
        "must carry the corrected action\\)",
    ):
        _load(root, into=buffer) if stream else _load(root)
    assert len(buffer) == 0


def test_interventions_with_no_action_feature_are_refused(tmp_path):
    root, _ = lerobot_recording(tmp_path, features=("observation.state", "intervention"))
    with pytest.raises(
        ValueError, match=r"episode 0, frame 1: an intervention frame without its corrected action"
    ):
        _load(root)


@pytest.mark.parametrize("stream", [False, True])
def test_rounds_out_of_order_are_refused_and_nothing_earlier_is_added(tmp_path, stream):
    rows = dagger_rows(rounds=(0, 1, 2, 3, 4), length=LENGTH)
    root = _foreign(rows, tmp_path)
    rounds = rows[keys.ROUND].numpy().copy()
    rounds[4 * LENGTH :] = 1  # the fifth round's episode says round 1, after round 3
    _replace_column(root, "imitrl.round", pa.array(rounds))
    buffer = DemonstrationBuffer()
    with pytest.raises(
        ValueError, match=r"episode 4, frame 0: round 1 after round 3 \(episode 3\)"
    ):
        _load(root, into=buffer) if stream else _load(root)
    assert len(buffer) == 0


@pytest.mark.parametrize("stream", [False, True])
def test_a_round_past_the_most_dagger_rounds_is_refused_at_load(tmp_path, stream):
    """A hostile review: round 2**63 - 1 loaded, and ``imitrl dagger`` failed after its
    first fit counting on from it (an int64 overflow)."""
    from imitrl.limits import MAX_ROUNDS

    rows = dagger_rows(rounds=(0, 1), length=LENGTH)
    root = _foreign(rows, tmp_path)
    rounds = rows[keys.ROUND].numpy().copy()
    rounds[LENGTH:] = 2**63 - 1
    _replace_column(root, "imitrl.round", pa.array(rounds))
    with pytest.raises(
        ValueError, match=rf"episode 1, frame 0: round {2**63 - 1}, expected 0 .* to {MAX_ROUNDS}"
    ):
        _load(root, into=DemonstrationBuffer()) if stream else _load(root)


def test_a_round_that_changes_inside_an_episode_is_refused(tmp_path):
    rows = dagger_rows(rounds=(0, 1, 2), length=LENGTH)
    root = _foreign(rows, tmp_path)
    rounds = rows[keys.ROUND].numpy().copy()
    rounds[LENGTH + 3] = 2
    _replace_column(root, "imitrl.round", pa.array(rounds))
    with pytest.raises(
        ValueError, match=r"episode 1, frame 3: round 2, but the episode began with round 1"
    ):
        _load(root)


def test_a_dataset_imitrl_wrote_before_the_intervention_column_still_loads(tmp_path):
    rows = dagger_rows(rounds=(0, 1), length=LENGTH)
    root = _foreign(rows, tmp_path)
    table = pq.read_table(root / DATA)
    table = table.rename_columns(
        ["imitrl.expert_executed" if c == "intervention" else c for c in table.column_names]
    )
    pq.write_table(table, root / DATA)
    info = json.loads((root / "meta/info.json").read_text())
    info["features"] = {
        ("imitrl.expert_executed" if k == "intervention" else k): v
        for k, v in info["features"].items()
    }
    (root / "meta/info.json").write_text(json.dumps(info))
    got = _load(root).rows
    assert torch.equal(got[keys.EXPERT_EXECUTED], rows[keys.EXPERT_EXECUTED])


def test_a_dataset_lerobot_records_with_interventions_loads_with_them(tmp_path):
    """As LeRobot's DAgger strategy records one: ``LeRobotDataset.create`` with its
    ``intervention`` feature, ``add_frame`` per step, ``save_episode`` per episode (where
    lerobot is installed, with its dataset extra; 0.6.1 checked)."""
    pytest.importorskip("lerobot.datasets")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (3,), "names": None},
        "action": {"dtype": "float32", "shape": (2,), "names": None},
        "intervention": {"dtype": "bool", "shape": (1,), "names": None},  # DAggerStrategyConfig's
    }
    writer = LeRobotDataset.create("imitrl/rollout_dagger", fps=10, root=tmp_path / "rec",
                                   features=features, use_videos=False)  # fmt: skip
    g = np.random.default_rng(0)
    flags = [[False, False, True, True, False], [True, True, False, False, False, True]]
    for pattern in flags:
        for flag in pattern:
            writer.add_frame({
                "observation.state": g.standard_normal(3).astype(np.float32),
                "action": g.standard_normal(2).astype(np.float32),
                "intervention": np.array([flag]),
                "task": "reach the cube",
            })  # fmt: skip
        writer.save_episode()
    writer.finalize()
    rows = _load(tmp_path / "rec").rows
    want = torch.tensor([f for pattern in flags for f in pattern])
    assert torch.equal(rows[keys.EXPERT_EXECUTED].reshape(-1), want)
    assert rows[keys.EPISODE].tolist() == [0] * 5 + [1] * 6

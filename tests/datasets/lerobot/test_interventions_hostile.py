"""LeRobot intervention columns a hostile review found mishandled: a flag of two values a
frame (a traceback), imitrl's episode ids that no longer follow LeRobot's episodes after a
merge (two episodes silently read as one), and both of imitrl's names for the intervention
column at once (an error naming neither)."""

from __future__ import annotations

import json
import warnings

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from imitrl import keys
from imitrl.datasets import load_lerobot
from tests.datasets.lerobot.test_dagger import dagger_rows
from tests.datasets.lerobot.test_interventions import (
    DATA,
    LENGTH,
    _foreign,
    _replace_column,
    lerobot_recording,
)


def test_an_intervention_flag_of_two_values_a_frame_is_one_line(tmp_path):
    root, rows = lerobot_recording(tmp_path)
    flags = rows[keys.EXPERT_EXECUTED].numpy()
    pairs = pa.array([[bool(f), bool(f)] for f in flags], pa.list_(pa.bool_(), 2))
    _replace_column(root, "intervention", pairs)
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["intervention"]["shape"] = [2]
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"'intervention' holds \(2,\) values a frame"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            load_lerobot(root)


@pytest.mark.parametrize("stream", [False, True])
def test_imitrl_episode_ids_that_do_not_follow_lerobots_episodes_give_way(tmp_path, stream):
    rows = dagger_rows(rounds=(0, 1, 2), length=LENGTH)
    root = _foreign(rows, tmp_path)
    table = pq.read_table(root / DATA)
    assert "imitrl.episode" in table.column_names
    merged = [0] * (2 * LENGTH) + [1] * LENGTH  # two datasets' ids, as a merge leaves them
    _replace_column(root, "imitrl.episode", pa.array(merged, pa.int64()))
    with pytest.warns(UserWarning, match="do not follow LeRobot's episodes one to one"):
        if stream:
            from imitrl.data import DemonstrationBuffer

            buffer = DemonstrationBuffer()
            load_lerobot(root, into=buffer)
            got = buffer.data
        else:
            got = load_lerobot(root).rows
    assert torch.equal(got[keys.EPISODE].unique(), torch.arange(3))  # LeRobot's three
    assert torch.equal(got[keys.STEP], torch.arange(LENGTH).repeat(3))


def test_both_names_of_the_intervention_column_are_named_with_the_file(tmp_path):
    root, _ = lerobot_recording(tmp_path)
    table = pq.read_table(root / DATA)
    table = table.append_column("imitrl.expert_executed", table.column("intervention"))
    pq.write_table(table, root / DATA)
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["imitrl.expert_executed"] = dict(info["features"]["intervention"])
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"info\.json: features \['imitrl\.expert_executed', "
                                         r"'intervention'\] all map to"):  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            load_lerobot(root)

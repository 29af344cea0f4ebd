"""LeRobot intervention columns a hostile review found mishandled: a flag of two values a
frame (a traceback), imitrl's episode ids that no longer follow LeRobot's episodes after a
merge (two episodes silently read as one), and both of imitrl's names for the intervention
column at once (an error naming neither)."""

from __future__ import annotations

import json
import warnings

import numpy as np
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


@pytest.mark.parametrize(
    "ids", [(7, 8, 7), (0, 1, 1), (10, 11, 12)], ids=["repeat-across", "repeat-next", "own"]
)
def test_a_stream_decides_on_imitrl_episode_ids_for_the_whole_dataset(tmp_path, monkeypatch, ids):
    """A hostile review: a stream read in pieces checked imitrl's ids piece by piece, so ids
    unique in each piece but repeated across pieces (a merge) were refused ("episode id 7 is
    already used") where the whole-dataset load takes LeRobot's ids with a warning."""
    import imitrl.datasets.lerobot._stream as stream
    from imitrl.data import DemonstrationBuffer

    monkeypatch.setattr(stream, "PIECE_ROWS", 2 * LENGTH)  # pieces of episodes {0, 1}, {2}
    root = _foreign(dagger_rows(rounds=(0, 1, 2), length=LENGTH), tmp_path)
    _replace_column(root, "imitrl.episode", pa.array(np.repeat(ids, LENGTH), pa.int64()))
    kept = len(set(ids)) == 3
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        whole = load_lerobot(root).rows[keys.EPISODE]
        buffer = DemonstrationBuffer()
        load_lerobot(root, into=buffer)
    said = [w for w in caught if "do not follow LeRobot's episodes one to one" in str(w.message)]
    assert len(said) == (0 if kept else 2)  # once for each load
    assert torch.equal(buffer.data[keys.EPISODE], whole)
    want = torch.tensor(ids) if kept else torch.arange(3)
    assert torch.equal(whole.unique_consecutive(), want)


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

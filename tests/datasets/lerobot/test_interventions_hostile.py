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


def _ids_column(root, ids) -> None:
    """``imitrl.episode`` rewritten to ``ids``, one per episode (a float column declared so)."""
    column = np.repeat(np.asarray(ids), LENGTH)
    dtype = "float32" if column.dtype.kind == "f" else None
    array = pa.array(column.astype(np.float32) if dtype else column.astype(np.int64))
    _replace_column(root, "imitrl.episode", array, dtype)


def _both_loads(root):
    """(the whole-dataset load's rows, a streamed load's rows, warnings of the two)."""
    from imitrl.data import DemonstrationBuffer

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        whole = load_lerobot(root).rows
        buffer = DemonstrationBuffer()
        load_lerobot(root, into=buffer)
    said = [w for w in caught if "do not follow LeRobot's episodes one to one" in str(w.message)]
    return whole, buffer.data, said


@pytest.mark.parametrize(
    "ids",
    [(7, 8, 7), (0, 1, 1), (3, 0, 1), (2, 1, 0), (-5, -4, -3), (10.5, 10.25, 12.75), (10, 11, 12)],
    ids=["repeat-across", "repeat-next", "unordered", "descending", "negative", "fractional",
         "own"],
)  # fmt: skip
def test_a_stream_decides_on_imitrl_episode_ids_for_the_whole_dataset(tmp_path, monkeypatch, ids):
    """Two hostile reviews: a stream read in pieces checked imitrl's ids piece by piece, so
    ids unique in each piece but repeated (or out of order) across pieces were refused
    ("episode id 7 is already used") where the whole load took LeRobot's ids; fractional
    ids were cut to integers, two episodes joined under one id; negative ones passed the
    whole load into rows no buffer accepts."""
    import imitrl.datasets.lerobot._stream as stream

    monkeypatch.setattr(stream, "PIECE_ROWS", LENGTH)  # a piece an episode
    root = _foreign(dagger_rows(rounds=(0, 1, 2), length=LENGTH), tmp_path)
    _ids_column(root, ids)
    whole, streamed, said = _both_loads(root)
    kept = list(ids) == sorted(set(ids)) and min(ids) >= 0 and all(i == int(i) for i in ids)
    assert len(said) == (0 if kept else 2)  # once for each load
    assert torch.equal(streamed[keys.EPISODE], whole[keys.EPISODE])
    want = torch.tensor([int(i) for i in ids]) if kept else torch.arange(3)
    assert torch.equal(whole[keys.EPISODE].unique_consecutive(), want)
    assert torch.equal(whole[keys.STEP], torch.arange(LENGTH).repeat(3))


def test_ids_past_the_largest_after_first_episode_are_refused_not_wrapped(tmp_path):
    """A hostile review: ``episode + first_episode`` wrapped to negative ids (int64), or at
    2**31 for an int32 column, without an error."""
    from imitrl.data import DemonstrationBuffer

    root = _foreign(dagger_rows(rounds=(0, 1, 2), length=LENGTH), tmp_path)
    big = 2**63 - 1
    _ids_column(root, (big - 4, big - 3, big - 2))
    for load in (lambda: load_lerobot(root, first_episode=5),
                 lambda: load_lerobot(root, first_episode=5, into=DemonstrationBuffer())):  # fmt: skip
        with pytest.raises(ValueError, match=r"\+ first_episode 5 passes the largest episode id"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                load()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert int(load_lerobot(root, first_episode=1).rows[keys.EPISODE].max()) == big - 1


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

"""What ``save_lerobot`` checks before its first frame: rows it writes load back (a review:
an episode past about 1024 s at fps 50 was written with float32 timestamps LeRobot's
1e-4 s check refuses; NaN was written and then refused at load, naming an element, not a
frame, and calling every value an intervention's action)."""

from __future__ import annotations

import pytest

from imitrl import keys
from imitrl.datasets import load_lerobot, save_lerobot
from imitrl.datasets.lerobot._write_plan import check_timestamps
from tests.datasets.test_datasets_faults import _rows


@pytest.mark.parametrize(("fps", "fine", "refused"), [(50, 51_204, 51_205), (10, 20_480, 30_000)])
def test_episodes_whose_float32_timestamps_lerobot_refuses_are_not_written(fps, fine, refused):
    check_timestamps(fine, fps)
    with pytest.raises(ValueError, match=rf"an episode of {refused} frames at fps {fps}"):
        check_timestamps(refused, fps)


def test_a_long_episode_is_refused_before_anything_is_written(tmp_path):
    n = 51_205
    rows = _rows(0, lengths=(n,))
    with pytest.raises(ValueError, match="split the episodes into parts of at most 51204 frames"):
        save_lerobot(rows, tmp_path / "ds", fps=50)
    assert not (tmp_path / "ds").exists()
    save_lerobot(rows[: n - 1], tmp_path / "ok", fps=50)  # one frame shorter: written, loaded
    assert load_lerobot(tmp_path / "ok").rows.shape[0] == n - 1


@pytest.mark.parametrize("key", [keys.OBSERVATION, (keys.NEXT, keys.REWARD)])
def test_nan_in_the_rows_is_refused_at_save_naming_episode_and_step(tmp_path, key):
    rows = _rows(0, lengths=(3, 4))
    value = rows.get(key).clone()
    value[5] = float("nan")  # episode 1, step 2
    rows.set(key, value)
    name = key if isinstance(key, str) else ".".join(key)
    with pytest.raises(ValueError, match=rf"'{name}' at episode 1, step 2 holds NaN or inf"):
        save_lerobot(rows, tmp_path / "ds", fps=10)
    assert not (tmp_path / "ds").exists()


def test_nan_in_a_file_is_named_by_its_frame_not_an_element(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    save_lerobot(_rows(0, lengths=(3, 4)), tmp_path / "ds", fps=10)
    (data,) = (tmp_path / "ds" / "data").rglob("*.parquet")
    table = pq.read_table(data)
    state = [list(v) for v in table.column("observation.state").to_pylist()]
    state[5][2] = float("nan")  # row 5: episode 1, frame 2; element 22 of the flat column
    i = table.column_names.index("observation.state")
    table = table.set_column(i, "observation.state", pa.array(state, table.schema.field(i).type))
    pq.write_table(table, data)
    (tmp_path / "ds" / "meta" / "imitrl.json").unlink()  # as another tool writes it
    with pytest.raises(ValueError) as err:
        load_lerobot(tmp_path / "ds")
    said = str(err.value)
    assert "frame 5 holds nan" in said and "(episode 1, frame 2)" in said, said
    assert "intervention" not in said

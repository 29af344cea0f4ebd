"""A disk buffer resumes only what it committed (a hostile review: a kill between the first
write and its commit left the folder unusable for good; a layout edited to claim more
rows resumed zeros the buffer never wrote as rows)."""

from __future__ import annotations

import json

import pytest
import torch

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from tests.data.test_disk import cartpole_rows


def test_a_first_write_killed_before_its_commit_leaves_a_folder_that_resumes(tmp_path, monkeypatch):
    path = tmp_path / "buf"
    buf = DemonstrationBuffer(path=path, capacity=16)
    monkeypatch.setattr(DemonstrationBuffer, "_commit", lambda self: (_ for _ in ()).throw(
        KeyboardInterrupt()))  # fmt: skip
    with pytest.raises(KeyboardInterrupt):  # the rows written, the layout not: a kill there
        buf.extend(cartpole_rows(12))
    monkeypatch.undo()
    del buf
    assert any((path / "storage").iterdir())  # the uncommitted column files
    assert json.loads((path / "imitrl_buffer.json").read_text())["columns"] == []
    again = DemonstrationBuffer(path=path, resume=True)
    assert len(again) == 0
    again.extend(cartpole_rows(5))  # was: "the file ... .memmap already exists", for good
    assert len(again) == 5 and torch.equal(again.data[keys.EPISODE], cartpole_rows(5)[keys.EPISODE])


@pytest.mark.parametrize(
    "rows, said", [(16, "stored rows are not a buffer's"), (10, "records 1 episodes")]
)
def test_a_layout_claiming_other_rows_than_its_episodes_is_refused(tmp_path, rows, said):
    path = tmp_path / "buf"
    buf = DemonstrationBuffer(path=path, capacity=16)
    buf.extend(cartpole_rows(10))  # episodes 0 (7 rows) and 1 (3 rows)
    del buf
    layout = json.loads((path / "imitrl_buffer.json").read_text())
    layout["rows"] = rows  # 16: six rows of zeros (episode 0 again)
    if rows == 10:  # the rows as written, one episode fewer recorded
        layout["num_episodes"] = 1
    (path / "imitrl_buffer.json").write_text(json.dumps(layout))
    with pytest.raises(ValueError, match=said):
        DemonstrationBuffer(path=path, resume=True)


@pytest.mark.parametrize("edit", [("observation", 0, "float64"), ("observation", 1, [5])])
def test_a_layout_whose_schema_is_not_its_columns_is_refused_on_resume(tmp_path, edit):
    """A hostile review: a schema edited to float64 (or shape [5]) resumed; float64 rows
    then passed its checks and failed in the write, counted all the same."""
    path = tmp_path / "buf"
    buf = DemonstrationBuffer(path=path)
    buf.extend(cartpole_rows(6))
    del buf
    layout = json.loads((path / "imitrl_buffer.json").read_text())
    name, field, value = edit
    layout["schema"][name][field] = value
    (path / "imitrl_buffer.json").write_text(json.dumps(layout))
    with pytest.raises(ValueError, match="its layout's schema is not what its column files hold"):
        DemonstrationBuffer(path=path, resume=True)


@pytest.mark.parametrize("disk", [False, True])
def test_a_write_that_fails_part_way_counts_nothing(tmp_path, monkeypatch, disk):
    """A hostile review: a failed write left ``len`` past the rows that exist, and every
    later extend was refused. Fault injected: the storage's write raises after it ran."""
    buf = DemonstrationBuffer(path=tmp_path / "buf" if disk else None)
    buf.extend(cartpole_rows(6))
    before = buf.data.clone()
    original = type(buf._rb).extend

    def failing(self, rows, *args, **kwargs):
        original(self, rows, *args, **kwargs)
        raise RuntimeError("disk full")

    monkeypatch.setattr(type(buf._rb), "extend", failing)
    with pytest.raises(RuntimeError, match="disk full"):
        buf.extend(cartpole_rows(4, first_episode=buf.next_episode))
    monkeypatch.undo()
    assert len(buf) == before.shape[0] and (buf.data == before).all()
    buf.extend(cartpole_rows(4, first_episode=buf.next_episode))  # the buffer goes on
    assert len(buf) == before.shape[0] + cartpole_rows(4).shape[0]
    assert (buf.data[: before.shape[0]] == before).all()


def test_a_folder_holding_only_a_buffers_lock_starts_afresh(tmp_path):
    """A kill between the lock's creation and the first layout leaves the lock alone. A
    hostile review: resume said "holds no disk buffer" and a fresh start "already holds
    other files (['imitrl_buffer.lock']) ... pass resume=True": each sent to the other."""
    path = tmp_path / "buf"
    path.mkdir()
    (path / "imitrl_buffer.lock").touch()
    with pytest.raises(ValueError, match="only the lock of one that stopped before it stored"):
        DemonstrationBuffer(path=path, resume=True)
    buf = DemonstrationBuffer(path=path, capacity=16)
    buf.extend(cartpole_rows(5))
    with pytest.raises(ValueError, match="in use by another disk buffer"):  # held: refused
        DemonstrationBuffer(path=path, resume=True)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").touch()
    with pytest.raises(ValueError, match=r"other files \(\['notes.txt'\]\)"):
        DemonstrationBuffer(path=tmp_path / "other", capacity=16)


def test_a_folder_planted_at_the_locks_name_is_one_line(tmp_path):
    """A hostile review: a raw IsADirectoryError from the lock's open."""
    path = tmp_path / "buf"
    (path / "imitrl_buffer.lock").mkdir(parents=True)
    with pytest.raises(ValueError, match="is a folder where a disk buffer's lock should be a file"):
        DemonstrationBuffer(path=path, capacity=4)


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (lambda lay: lay["columns"][0].update(dtype="qint8"), "'qint8' is not a dtype a buffer"),
        (lambda lay: lay["columns"][0].update(dtype="uint16"), "'uint16' is not a dtype a buffer"),
        (lambda lay: lay.update(num_states="x"), "num_states must be null or an integer >= 1"),
        (lambda lay: lay.update(num_states=-3), "num_states must be null or an integer >= 1"),
        (lambda lay: lay.update(rows=0), "2 episodes in 0 rows"),
    ],
)  # fmt: skip
def test_a_layout_whose_fields_are_not_a_buffers_is_one_line(tmp_path, edit, said):
    """A hostile review: qint8 was torch's 4 KB dispatcher dump; num_states "x" or -3
    resumed, refused only at the next extend; rows 0 resumed with an episode in it."""
    path = tmp_path / "buf"
    buf = DemonstrationBuffer(path=path, capacity=16)
    buf.extend(cartpole_rows(10))
    del buf
    layout = json.loads((path / "imitrl_buffer.json").read_text())
    edit(layout)
    (path / "imitrl_buffer.json").write_text(json.dumps(layout))
    with pytest.raises(ValueError, match="not a readable disk buffer layout") as err:
        DemonstrationBuffer(path=path, resume=True)
    assert said in str(err.value) and "\n" not in str(err.value)


def test_a_resume_with_an_action_spec_checks_the_stored_rows_as_load_does(tmp_path):
    """A hostile review: resuming with a tighter spec kept rows outside it (load refused)."""
    from torchrl.data import Categorical

    path = tmp_path / "buf"
    buf = DemonstrationBuffer(path=path, capacity=16)
    buf.extend(cartpole_rows(10))  # actions 0 and 1
    del buf
    assert len(DemonstrationBuffer(path=path, resume=True, action_spec=Categorical(2))) == 10
    with pytest.raises(ValueError, match=r"stored rows: .* holds action 1, outside \[0, 1\)"):
        DemonstrationBuffer(path=path, resume=True, action_spec=Categorical(1))

"""Buffer checkpoints: rows not capacity, verified before read, atomic, never written by load.

Each test is one row of the fault table (case -> behaviour). Every refused load also
checks that the checkpoint directory and its parent are byte-identical afterwards.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import signal
import warnings
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.fs import publish
from imitrl.learners import TaskSpec, build


# ---------------------------------------------------------------------- helpers
def demo_rows(n: int, first_episode: int = 0, *, seed: int = 0, length: int = 5) -> TensorDict:
    """``n`` FrozenLake-shaped rows, episodes of ``length`` steps from ``first_episode``."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randint(0, 4, (n,), generator=g)
    return TensorDict(
        {
            keys.OBSERVATION: torch.randint(0, 16, (n,), generator=g),
            keys.EXPERT_ACTION: a,
            keys.ACTION: a.clone(),
            keys.EXPERT_EXECUTED: torch.rand(n, generator=g) < 0.5,
            keys.EPISODE: first_episode + torch.arange(n) // length,
            keys.ROUND: torch.zeros(n, dtype=torch.long),
            keys.STEP: torch.arange(n) % length,
            (keys.NEXT, keys.REWARD): torch.randn(n, 1, generator=g),
        },
        [n],
    )


def checkpoint_tree(path: Path) -> dict[str, tuple[int, str, int]]:
    """Every entry under ``path`` and beside it: ``name -> (size, sha256, mtime_ns)``."""
    out = {}
    for root in (path.parent, path):
        if not root.is_dir():
            continue
        for entry in sorted(root.iterdir()):
            info = entry.lstat()
            digest = hashlib.sha256(entry.read_bytes()).hexdigest() if entry.is_file() else ""
            out[str(entry)] = (info.st_size, digest, info.st_mtime_ns)
    return out


def same_buffer(a: DemonstrationBuffer, b: DemonstrationBuffer) -> bool:
    return (
        len(a) == len(b)
        and a.schema == b.schema
        and a.next_episode == b.next_episode
        and bool((a.data == b.data).all())
    )


def same_state(a, b) -> bool:
    """Nested dicts/lists of tensors and plain values, equal to the bit."""
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return (
            isinstance(b, dict) and a.keys() == b.keys() and all(same_state(a[k], b[k]) for k in a)
        )
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same_state(x, y) for x, y in zip(a, b))
    return a == b


def refused(path: Path, match: str, **load_kwargs) -> ValueError:
    """Load ``path`` expecting a ValueError matching ``match``; nothing on disk may change."""
    before = checkpoint_tree(path)
    with pytest.raises(ValueError, match=match) as info:
        DemonstrationBuffer.load(path, **load_kwargs)
    assert checkpoint_tree(path) == before, "a refused load changed the checkpoint"
    return info.value


@pytest.fixture
def saved(tmp_path: Path) -> tuple[Path, DemonstrationBuffer]:
    buf = DemonstrationBuffer(capacity=64)
    buf.extend(demo_rows(40))
    return buf.save(tmp_path / "ck", state={"round": 1}), buf


def _column(path: Path, key: str) -> Path:
    content = json.loads((path / "manifest.json").read_text())["content"]
    (name,) = [c["file"] for c in content["columns"] if c["key"] == [key]]
    return path / name


# ------------------------------------------------------------------- round trip
def test_rows_learner_optimizer_and_state_round_trip(tmp_path):
    buf = DemonstrationBuffer(capacity=8, action_spec=Categorical(4), num_states=16)
    for k in range(3):
        buf.extend(demo_rows(7 + k, buf.next_episode, seed=k))
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))
    fit_bc(learner, buf, BCConfig(num_steps=3))
    path = buf.save(tmp_path / "ck", learner=learner, state={"round": 2, "beta": [0.5, None]})
    assert path == (tmp_path / "ck").absolute()
    twin = build("cross_entropy", TaskSpec(action=4, num_states=16), lr=0.3)
    before = checkpoint_tree(path)
    again, state = DemonstrationBuffer.load(path, learner=twin, action_spec=Categorical(4))
    assert checkpoint_tree(path) == before  # loading writes nothing
    assert same_buffer(again, buf) and again.num_states == 16
    assert state == {"round": 2, "beta": [0.5, None]}
    for a, b in zip(learner.state_dict().values(), twin.state_dict().values()):
        assert torch.equal(a, b)
    assert same_state(twin.opt_pi.state_dict(), learner.opt_pi.state_dict())
    index = again.extend(demo_rows(3, again.next_episode))  # lands after the loaded rows
    assert torch.equal(index, torch.arange(len(buf), len(buf) + 3))


def test_the_checkpoint_holds_the_rows_not_the_capacity(tmp_path):
    buf = DemonstrationBuffer(capacity=1 << 16)
    buf.extend(demo_rows(1000))
    path = buf.save(tmp_path / "ck")
    manifest = json.loads((path / "manifest.json").read_text())["content"]
    columns = {c["file"] for c in manifest["columns"]}
    data_bytes = sum((path / name).stat().st_size for name in columns)
    assert data_bytes == buf.data.bytes() == 1000 * (6 * 8 + 1 + 4)  # six int64, bool, float
    total = sum(f.stat().st_size for f in path.iterdir())
    assert total < data_bytes + 16_000  # the manifest and state: a few kB
    assert manifest["rows"] == 1000 and set(manifest["files"]) == set(os.listdir(path)) - {
        "manifest.json"
    }


# ---------------------------------------------------------------- damaged files
@pytest.mark.parametrize(
    "damage, match",
    [
        (lambda f: f.write_bytes(f.read_bytes()[: f.stat().st_size // 2]), "truncated"),
        (lambda f: f.write_bytes(b""), "truncated"),  # a zero-byte file
        (lambda f: f.write_bytes(f.read_bytes() + bytes(8)), "appended"),  # extra zero bytes
        (lambda f: f.write_bytes(_flip(f.read_bytes(), 17)), "SHA-256 does not match"),
        (lambda f: f.unlink(), "missing"),
        (lambda f: (f.unlink(), f.symlink_to(f.with_name("state.json"))), "not a regular file"),
    ],
    ids=["truncated", "zero-byte", "appended-zeros", "altered", "missing", "symlink"],
)
def test_a_damaged_column_is_refused_by_name_and_left_as_it_is(saved, damage, match):
    path, _ = saved
    column = _column(path, keys.OBSERVATION)
    damage(column)
    err = refused(path, match)
    assert column.name in str(err)


def _flip(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1 :]


def test_an_unlisted_file_is_refused_by_name(saved):
    path, _ = saved
    (path / "notes.txt").write_text("hello")
    assert "notes.txt" in str(refused(path, "does not list"))


def test_an_edited_manifest_is_refused(saved):
    path, _ = saved
    manifest_path = path / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["content"]["rows"] = 20  # consistent-looking, but the checksum disagrees
    manifest_path.write_text(json.dumps(manifest))
    refused(path, r"manifest\.json: edited or damaged")
    manifest["format"] = "imitrl.DemonstrationBuffer/2"
    manifest_path.write_text(json.dumps(manifest))
    refused(path, r"manifest\.json: format 'imitrl\.DemonstrationBuffer/2'")
    manifest_path.unlink()
    refused(path, r"not a saved DemonstrationBuffer \(no manifest\.json\)")


def test_stored_rows_pass_the_buffers_checks(saved):
    path, _ = saved  # actions 0..3 do not fit a 2-action spec given at load
    refused(path, "fail the buffer's checks.*outside", action_spec=Categorical(2))


# ---------------------------------------------------------------------- learner
def test_a_damaged_or_mismatched_learner_is_refused_and_left_unchanged(tmp_path):
    buf = DemonstrationBuffer()
    buf.extend(demo_rows(20))
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))
    fit_bc(learner, buf, BCConfig(num_steps=2))
    path = buf.save(tmp_path / "ck", learner=learner)
    plain = buf.save(tmp_path / "plain")

    def check(target, path, match):
        weights, opt = copy.deepcopy(target.state_dict()), copy.deepcopy(target.opt_pi.state_dict())
        refused(path, match, learner=target)
        assert same_state(target.state_dict(), weights)
        assert same_state(target.opt_pi.state_dict(), opt)

    check(
        build("cross_entropy", TaskSpec(action=4, num_states=16)),
        plain,
        "cannot load the learner: the checkpoint was saved without",
    )
    check(
        build("cross_entropy", TaskSpec(action=3, num_states=16)),
        path,
        r"learner\.pt: cannot load learner into the given",
    )
    (path / "opt_pi.pt").write_bytes(_flip((path / "opt_pi.pt").read_bytes(), 40))
    check(
        build("cross_entropy", TaskSpec(action=4, num_states=16)),
        path,
        r"opt_pi\.pt: SHA-256 does not match",
    )


# ------------------------------------------------------------------------ save
def test_save_refuses_state_that_json_would_change(tmp_path):
    buf = DemonstrationBuffer()
    buf.extend(demo_rows(5))
    for state in ({"beta": (0.5, 0.25)}, {1: "a"}, {"x": float("nan")}, {"t": torch.zeros(1)}):
        with pytest.raises(ValueError, match="JSON"):
            buf.save(tmp_path / "ck", state=state)
    assert not (tmp_path / "ck").exists() and os.listdir(tmp_path) == []
    with pytest.raises(ValueError, match="empty"):
        DemonstrationBuffer().save(tmp_path / "ck")


def test_save_replaces_only_a_checkpoint_or_an_empty_directory(tmp_path, monkeypatch):
    buf = DemonstrationBuffer()
    buf.extend(demo_rows(5))
    user = tmp_path / "user"
    user.mkdir()
    (user / "thesis.tex").write_text("years of work")
    afile = tmp_path / "afile"
    afile.write_text("x")
    before = checkpoint_tree(user)
    with pytest.raises(ValueError, match="exists; pass overwrite=True"):
        buf.save(user)
    for target, match in ((user, "not a readable checkpoint"), (afile, "not a directory")):
        with pytest.raises(ValueError, match=match):
            buf.save(target, overwrite=True)
    assert checkpoint_tree(user) == before and afile.read_text() == "x"
    ck = buf.save(tmp_path / "ck")
    with pytest.raises(ValueError, match="exists; pass overwrite=True"):
        buf.save(ck)  # a checkpoint is replaced only when asked
    (ck / "notes.txt").write_text("mine")  # a checkpoint holding a user's file is kept
    with pytest.raises(ValueError, match="does not list"):
        buf.save(ck, overwrite=True)
    (ck / "notes.txt").unlink()
    monkeypatch.chdir(ck)  # the working directory is never replaced
    with pytest.raises(ValueError, match="working directory"):
        buf.save(".")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty").mkdir()
    assert same_buffer(DemonstrationBuffer.load(buf.save("empty"))[0], buf)


def test_save_over_a_checkpoint_replaces_it_whole(tmp_path):
    first, second = DemonstrationBuffer(), DemonstrationBuffer()
    first.extend(demo_rows(10))
    second.extend(demo_rows(25, seed=1))
    path = first.save(tmp_path / "ck", state={"n": 1})
    second.save(path, state={"n": 2}, overwrite=True)
    again, state = DemonstrationBuffer.load(path)
    assert same_buffer(again, second) and state == {"n": 2}
    assert sorted(os.listdir(tmp_path)) == ["ck"]  # no temporary or old copy left


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two-renames"])
def test_an_error_at_any_point_of_a_save_leaves_the_previous_checkpoint(
    tmp_path, monkeypatch, exchange
):
    old, new = DemonstrationBuffer(), DemonstrationBuffer()
    old.extend(demo_rows(10))
    new.extend(demo_rows(30, seed=3))
    path = old.save(tmp_path / "ck")
    if not exchange:
        monkeypatch.setattr(publish, "exchange", lambda a, b: False)
    points = _count_fsyncs(lambda: new.save(tmp_path / "probe"), monkeypatch)
    real_fsync = os.fsync
    for k in range(1, points + 1):
        calls = []

        def failing(fd, k=k, calls=calls):
            calls.append(fd)
            if len(calls) == k:
                raise OSError(5, "injected I/O error")
            real_fsync(fd)

        monkeypatch.setattr(os, "fsync", failing)
        with pytest.raises(OSError, match="injected"):
            new.save(path, overwrite=True)
        monkeypatch.setattr(os, "fsync", real_fsync)
        loaded = DemonstrationBuffer.load(path)[0]
        # the last fsync is the parent's, after the swap: by then the new one is in place
        assert same_buffer(loaded, new if k == points else old), k
        assert sorted(os.listdir(tmp_path)) == ["ck", "probe"], k
        old.save(path, overwrite=True)


def _count_fsyncs(save, monkeypatch) -> int:
    calls = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (calls.append(fd), real(fd))[1])
    save()
    monkeypatch.setattr(os, "fsync", real)
    return len(calls)


def _killed_save(buf: DemonstrationBuffer, path: Path, kill_at: int, *, exchange: bool) -> None:
    """Save in a forked child that SIGKILLs itself at its ``kill_at``-th fsync."""
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        try:
            calls = []
            real = os.fsync

            def dying(fd):
                calls.append(fd)
                if len(calls) == kill_at:
                    os.kill(os.getpid(), signal.SIGKILL)
                real(fd)

            os.fsync = dying
            if not exchange:
                publish.exchange = lambda a, b: False
            buf.save(path, overwrite=True)
        finally:
            os._exit(0)
    _, status = os.waitpid(pid, 0)
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL


def test_kill_9_at_every_fsync_of_a_save_leaves_a_whole_checkpoint(tmp_path, monkeypatch):
    old, new = DemonstrationBuffer(), DemonstrationBuffer()
    old.extend(demo_rows(10))
    new.extend(demo_rows(30, seed=3))
    path = old.save(tmp_path / "ck")
    points = _count_fsyncs(lambda: new.save(tmp_path / "probe"), monkeypatch)
    for k in range(1, points + 1):
        _killed_save(new, path, k, exchange=True)
        loaded = DemonstrationBuffer.load(path)[0]
        assert same_buffer(loaded, new if k == points else old), k
        with warnings.catch_warnings():  # the killed save's leftovers are named
            warnings.simplefilter("ignore")
            old.save(path, overwrite=True)  # and the next save clears what the killed one left
        assert sorted(os.listdir(tmp_path)) == ["ck", "probe"], k


def test_kill_9_between_the_fallback_renames_names_the_previous_checkpoint(tmp_path, monkeypatch):
    old, new = DemonstrationBuffer(), DemonstrationBuffer()
    old.extend(demo_rows(10))
    new.extend(demo_rows(30, seed=3))
    path = old.save(tmp_path / "ck")
    real_rename = os.rename
    pid = os.fork()
    if pid == 0:
        try:
            seen = []

            def rename(a, b):
                seen.append(b)
                if len(seen) == 2:  # 1: ck -> .ck.imitrl-old-*, 2: tmp -> ck
                    os.kill(os.getpid(), signal.SIGKILL)
                real_rename(a, b)

            os.rename = rename
            publish.exchange = lambda a, b: False
            new.save(path, overwrite=True)
        finally:
            os._exit(0)
    os.waitpid(pid, 0)
    err = refused(path, r"an interrupted save left the previous checkpoint at .*\.ck\.imitrl-old-")
    aside = Path(str(err).split(" at ")[1].split(" (rename")[0])
    os.rename(aside, path)  # what the message says to do
    assert same_buffer(DemonstrationBuffer.load(path)[0], old)


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (lambda st: st["state"][0].update(exp_avg=torch.zeros(1).expand(2**40)), "[1099511627776]"),
        (lambda st: st["state"][0].update(step=torch.tensor(-5.0)), "or a negative step"),
        (lambda st: st["state"][0].update(exp_avg_sq=st["state"][0]["exp_avg_sq"] * float("nan")),
         "or not finite"),
        (lambda st: st["param_groups"][0].update(lr=float("nan")), "hyperparameters must be finite"),
        (lambda st: st["param_groups"][0].update(lr=-1.0), "lr >= 0"),
        (lambda st: st["state"].update({99: {}}), "a state of parameter 99"),
    ],
)  # fmt: skip
def test_an_edited_optimizer_state_is_refused_before_it_is_copied(tmp_path, edit, said):
    """A hostile review (the checksums redone): an exp_avg viewing one stored value as
    2^29 values was materialised (2.5 GB) and failed in a traceback, as did a negative
    step; a NaN learning rate was blamed on the state's JSON."""
    from tests.jobs.test_dagger_resume import _resigned

    buf = DemonstrationBuffer()
    buf.extend(demo_rows(20))
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))
    fit_bc(learner, buf, BCConfig(num_steps=2))
    path = buf.save(tmp_path / "ck", learner=learner)
    state = torch.load(path / "opt_pi.pt", weights_only=True)
    edit(state)
    torch.save(state, path / "opt_pi.pt")
    _resigned(path)
    target = build("cross_entropy", TaskSpec(action=4, num_states=16))
    opt = copy.deepcopy(target.opt_pi.state_dict())
    with pytest.raises(ValueError, match=r"opt_pi\.pt") as err:
        DemonstrationBuffer.load(path, learner=target)
    assert said in str(err.value), err.value
    assert same_state(target.opt_pi.state_dict(), opt)

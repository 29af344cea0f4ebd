"""Property-based tests (hypothesis) of the demonstration buffer and its checkpoint loader.

- a valid ``extend`` appends exactly its rows, at the end, and nothing else; the grown
  storage holds what a TorchRL storage allocated large enough from the start holds;
- an invalid ``extend`` (17 kinds of bad batch) raises ``ValueError`` and changes
  nothing: rows, length, capacity, schema, next episode, writer cursor;
- a damaged checkpoint (a file truncated at any byte, a byte flipped, a file deleted,
  bytes appended, the manifest edited, a file added) either loads identical rows, state
  and learner, or raises ``ValueError`` naming the file; the directory is byte-identical
  before and after.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, LazyTensorStorage, ReplayBuffer

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.compat import writer_cursor
from imitrl.data import REQUIRED_KEYS, DemonstrationBuffer
from imitrl.learners import TaskSpec, build
from tests.data.test_checkpoint import checkpoint_tree, demo_rows, same_buffer, same_state

# derandomize: the same examples on every run (a failure reproduces); no example database
FEW = settings(
    max_examples=10,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

KINDS = ("tabular", "continuous", "unchecked")  # with Categorical/Bounded spec, or none
episode_lengths = st.lists(st.integers(1, 6), min_size=1, max_size=3)


def make_buffer(kind: str, capacity: int) -> DemonstrationBuffer:
    if kind == "tabular":
        return DemonstrationBuffer(capacity=capacity, action_spec=Categorical(4), num_states=16)
    if kind == "continuous":
        return DemonstrationBuffer(capacity=capacity, action_spec=Bounded(-1.0, 1.0, shape=(2,)))
    return DemonstrationBuffer(capacity=capacity)


def make_rows(kind: str, lengths: list[int], first_episode: int, seed: int) -> TensorDict:
    """Whole episodes of ``lengths`` steps, ids from ``first_episode``, valid for ``kind``."""
    g = torch.Generator().manual_seed(seed)
    n = sum(lengths)
    if kind == "continuous":
        obs, a = torch.randn(n, 3, generator=g), torch.rand(n, 2, generator=g) * 2 - 1
    else:
        obs, a = torch.randint(0, 16, (n,), generator=g), torch.randint(0, 4, (n,), generator=g)
    episode = torch.repeat_interleave(torch.arange(len(lengths)), torch.tensor(lengths))
    return TensorDict(
        {
            keys.OBSERVATION: obs,
            keys.EXPERT_ACTION: a,
            keys.ACTION: a.clone(),
            keys.EXPERT_EXECUTED: torch.rand(n, generator=g) < 0.5,
            keys.EPISODE: first_episode + episode,
            keys.ROUND: torch.full((n,), seed % 3),
            keys.STEP: torch.cat([torch.arange(k) for k in lengths]),
            (keys.NEXT, keys.REWARD): torch.randn(n, 1, generator=g),
        },
        [n],
    )


def same_rows(a: TensorDictBase, b: TensorDictBase) -> bool:
    ka, kb = set(a.keys(True, True)), set(b.keys(True, True))
    return ka == kb and all(
        a.get(k).dtype == b.get(k).dtype and torch.equal(a.get(k), b.get(k)) for k in ka
    )


# ------------------------------------------------------------------ valid extends
@FEW
@given(
    kind=st.sampled_from(KINDS),
    capacity=st.integers(1, 8),
    batches=st.lists(st.tuples(episode_lengths, st.integers(0, 2)), min_size=1, max_size=5),
    seed=st.integers(0, 2**16),
)
def test_a_valid_extend_appends_exactly_its_rows(kind, capacity, batches, seed):
    buf = make_buffer(kind, capacity)
    total = sum(sum(lengths) for lengths, _ in batches)
    public = ReplayBuffer(storage=LazyTensorStorage(total))  # the public path: never full here
    for i, (lengths, gap) in enumerate(batches):
        rows = make_rows(kind, lengths, buf.next_episode + gap, seed + i)
        before, n0, n = (buf.data.clone() if len(buf) else None), len(buf), rows.shape[0]
        index = buf.extend(rows)
        assert torch.equal(index, torch.arange(n0, n0 + n))
        assert len(buf) == n0 + n <= buf.capacity
        assert before is None or same_rows(buf.data[:n0], before)
        assert same_rows(buf.data[n0:], rows)
        assert buf.next_episode == int(rows[keys.EPISODE].max()) + 1
        public.extend(rows)
    assert same_rows(buf.data, public[:total])  # grown by doubling == allocated at once
    assert buf.capacity >= total > capacity or buf.capacity == capacity


# ---------------------------------------------------------------- invalid extends
def _set(rows, key, value):
    rows.set(key, value)
    return rows


def _poison(value: float) -> Callable:
    def f(rows, buf, draw):
        reward = rows.get((keys.NEXT, keys.REWARD)).clone()
        reward[draw(st.integers(0, rows.shape[0] - 1))] = value
        return _set(rows, (keys.NEXT, keys.REWARD), reward)

    return f


def _drop_required(rows, buf, draw):
    return rows.exclude(draw(st.sampled_from(REQUIRED_KEYS)))


def _cast(key, dtype):
    return lambda rows, buf, draw: _set(rows, key, rows.get(key).to(dtype))


def _needs_schema(f):  # a change that is only wrong once the first extend fixed the schema
    def g(rows, buf, draw):
        assume(len(buf) > 0)
        return f(rows, buf, draw)

    return g


def _reuse_episode(rows, buf, draw):
    shift = buf.next_episode - int(rows[keys.EPISODE].min()) - draw(st.integers(1, 3))
    return _set(rows, keys.EPISODE, rows[keys.EPISODE] + shift)


def _split_episode(rows, buf, draw):
    assume(int(rows[keys.EPISODE][0]) != int(rows[keys.EPISODE][-1]))
    return torch.cat([rows, rows[:1]])  # the first episode reappears after another one


def _negative(key):
    def f(rows, buf, draw):
        value = rows.get(key).clone()
        value[draw(st.integers(0, rows.shape[0] - 1))] = -1
        return _set(rows, key, value)

    return f


def _bad_action(rows, buf, draw):
    assume(buf.action_spec is not None)
    label = draw(st.sampled_from([keys.ACTION, keys.EXPERT_ACTION]))
    value = rows.get(label).clone()
    value[draw(st.integers(0, rows.shape[0] - 1))] = 4 if value.dtype == torch.int64 else 1.5
    return _set(rows, label, value)


def _bad_state(rows, buf, draw):
    assume(buf.num_states is not None)
    obs = rows.get(keys.OBSERVATION).clone()
    obs[draw(st.integers(0, rows.shape[0] - 1))] = draw(st.sampled_from([16, -1]))
    return _set(rows, keys.OBSERVATION, obs)


MUTATIONS: dict[str, Callable] = {
    "nan": _poison(float("nan")),
    "inf": _poison(float("inf")),
    "-inf": _poison(-float("inf")),
    "missing required key": _drop_required,
    "missing extra key": _needs_schema(lambda r, b, d: r.exclude((keys.NEXT, keys.REWARD))),
    "unexpected key": _needs_schema(lambda r, b, d: _set(r, "task", torch.zeros(r.shape[0]))),
    "observation dtype": _needs_schema(_cast(keys.OBSERVATION, torch.float64)),
    "reward shape": _needs_schema(
        lambda r, b, d: _set(r, (keys.NEXT, keys.REWARD), torch.zeros(r.shape[0], 2))
    ),
    "int32 episode ids": _cast(keys.EPISODE, torch.int32),
    "int bool flag": _cast(keys.EXPERT_EXECUTED, torch.uint8),
    "float executed action": _cast(keys.ACTION, torch.float64),
    "episode id already used": _reuse_episode,
    "episode split in two": _split_episode,
    "negative round or step": lambda r, b, d: _negative(
        d(st.sampled_from([keys.ROUND, keys.STEP]))
    )(r, b, d),
    "action outside the spec": _bad_action,
    "state outside [0, S)": _bad_state,
    "not a row batch": lambda r, b, d: d(
        st.sampled_from([r[:0], r.unsqueeze(0), r.to_dict(), r.get(keys.OBSERVATION)])
    ),
}


@pytest.mark.parametrize("mutation", sorted(MUTATIONS))
@FEW
@given(
    kind=st.sampled_from(KINDS),
    capacity=st.integers(1, 8),
    prefill=st.lists(episode_lengths, max_size=2),
    lengths=episode_lengths,
    seed=st.integers(0, 2**16),
    data=st.data(),
)
def test_an_invalid_extend_raises_and_changes_nothing(
    mutation, kind, capacity, prefill, lengths, seed, data
):
    buf = make_buffer(kind, capacity)
    for i, part in enumerate(prefill):
        buf.extend(make_rows(kind, part, buf.next_episode, seed + 100 + i))
    good = make_rows(kind, lengths, buf.next_episode, seed)
    bad = MUTATIONS[mutation](good.clone(), buf, data.draw)
    snapshot = (buf.data.clone() if len(buf) else None, len(buf), buf.capacity, buf.next_episode)
    schema, cursor = buf.schema, writer_cursor(buf._rb)
    with pytest.raises(ValueError):
        buf.extend(bad)
    assert (len(buf), buf.capacity, buf.next_episode) == snapshot[1:]
    assert buf.schema == schema and writer_cursor(buf._rb) == cursor
    assert snapshot[0] is None or same_rows(buf.data, snapshot[0])
    n0 = len(buf)
    assert torch.equal(buf.extend(good), torch.arange(n0, n0 + good.shape[0]))  # still whole
    assert same_rows(buf.data[n0:], good)


# ------------------------------------------------------------- damaged checkpoints
@pytest.fixture(scope="module")
def saved_checkpoint(tmp_path_factory):
    """A checkpoint with every kind of file (rows, learner, optimizer, state) and its parts."""
    buf = DemonstrationBuffer(capacity=4)
    for k in range(3):
        buf.extend(demo_rows(6 + k, buf.next_episode, seed=k))
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))
    fit_bc(learner, buf, BCConfig(num_steps=2))
    state = {"round": 2, "beta": [1.0, 0.5]}
    path = buf.save(tmp_path_factory.mktemp("ck") / "ck", learner=learner, state=state)
    return path, buf, learner, state


def _leaves(value, where=()):
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _leaves(v, (*where, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _leaves(v, (*where, i))
    else:
        yield where, value


def _edit_manifest(path: Path, draw) -> str:
    manifest = json.loads((path / "manifest.json").read_text())
    where, value = draw(st.sampled_from(sorted(_leaves(manifest), key=str)))
    new = draw(
        st.one_of(st.integers(-3, 10**6), st.text(max_size=8), st.none(), st.booleans()).filter(
            lambda v: v != value or type(v) is not type(value)
        )
    )
    node = manifest
    for part in where[:-1]:
        node = node[part]
    node[where[-1]] = new
    (path / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return "manifest.json"


def _damage(path: Path, how: str, draw) -> str:
    """Damage one file of the checkpoint at ``path``; returns the name a refusal must give."""
    if how == "edit manifest":
        return _edit_manifest(path, draw)
    if how == "add file":
        name = draw(st.sampled_from(["column_999.bin", "notes.txt", ".hidden", "learner.pt.bak"]))
        (path / name).write_bytes(draw(st.binary(max_size=8)))
        return name
    target = path / draw(st.sampled_from(sorted(p.name for p in path.iterdir())))
    data = target.read_bytes()
    if how == "delete":
        target.unlink()
    elif how == "truncate":
        target.write_bytes(data[: draw(st.integers(0, len(data) - 1))])
    elif how == "append":
        target.write_bytes(data + draw(st.sampled_from([bytes(1), bytes(64), b"\x01"])))
    else:  # flip: one byte changed to any other value
        at, xor = draw(st.integers(0, len(data) - 1)), draw(st.integers(1, 255))
        target.write_bytes(data[:at] + bytes([data[at] ^ xor]) + data[at + 1 :])
    return target.name


@settings(FEW, max_examples=60)
@given(
    how=st.sampled_from(["truncate", "flip", "delete", "append", "edit manifest", "add file"]),
    data=st.data(),
)
def test_a_damaged_checkpoint_loads_identically_or_is_refused_by_name(saved_checkpoint, how, data):
    original, buf, learner, state = saved_checkpoint
    with tempfile.TemporaryDirectory() as scratch:
        path = Path(scratch) / "ck"
        shutil.copytree(original, path)
        name = _damage(path, how, data.draw)
        before = checkpoint_tree(path)
        twin = build("cross_entropy", TaskSpec(action=4, num_states=16))
        weights = {k: v.clone() for k, v in twin.state_dict().items()}
        try:
            loaded, loaded_state = DemonstrationBuffer.load(path, learner=twin)
        except ValueError as err:
            assert name in str(err), (how, name, str(err))
            assert same_state(twin.state_dict(), weights)  # a refused load changes no learner
        else:  # only a change JSON does not see (whitespace in the manifest) may load
            assert same_buffer(loaded, buf) and loaded_state == state
            assert same_state(twin.state_dict(), learner.state_dict())
            assert same_state(twin.opt_pi.state_dict(), learner.opt_pi.state_dict())
        assert checkpoint_tree(path) == before, "loading changed the checkpoint"

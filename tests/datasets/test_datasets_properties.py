"""Property: a corrupted dataset loads the original rows or raises ValueError, never anything else.

Corruptions (hypothesis draws them): truncate a file at a random byte, flip a random
bit, delete a random file, replace a random value of a JSON metadata file (Minari's
spaces, JSON inside JSON, included) with another JSON value or a near miss (an integer
off by one, another dtype name). The datasets: one :func:`save_lerobot` wrote (every file
checksummed in ``meta/imitrl.json``: any corruption at all must load identically or be
refused), LeRobot v2.1 and v3.0 datasets laid out as lerobot writes them, Minari hdf5
and arrow. Parquet, HDF5 and Arrow files carry no checksum of their own, so a flipped
bit inside their raw data is a different valid value that no reader can tell from the
original: for datasets not written by imitrl, bits are flipped in the JSON metadata
only (truncation, deletion and metadata changes reach every file). "Identical" means
the same keys, shapes and values; for those datasets a dtype may follow a changed
declaration when every value stays exact (``float32`` declared ``float64``).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from imitrl import keys
from imitrl.datasets import load_lerobot, load_minari, save_lerobot
from tests._lerobot_files import episodes_data, write_v21, write_v30
from tests.datasets.minari.test_minari import _episode, _write

SETTINGS = settings(
    max_examples=int(os.environ.get("IMITRL_PROPERTY_EXAMPLES", "300")),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize="IMITRL_PROPERTY_EXAMPLES" not in os.environ,  # fixed examples in CI
)
_JSON = (".json", ".jsonl")
_DTYPES = ["float16", "float32", "float64", "int8", "int32", "int64", "uint8", "bool", "image"]


# ------------------------------------------------------------------ datasets
def _imitrl_rows() -> TensorDict:
    g = torch.Generator().manual_seed(0)
    parts = []
    for e, n in enumerate([4, 3, 5]):
        done = torch.arange(n).eq(n - 1).unsqueeze(-1)
        label = torch.randint(0, 2, (n,), generator=g)
        parts.append(
            TensorDict(
                {
                    keys.OBSERVATION: torch.randn(n, 4, generator=g),
                    keys.EXPERT_ACTION: label,
                    keys.ACTION: 1 - label,
                    keys.EXPERT_EXECUTED: torch.zeros(n, dtype=torch.bool),
                    keys.EPISODE: torch.full((n,), e),
                    keys.ROUND: torch.full((n,), e),
                    keys.STEP: torch.arange(n),
                    (keys.NEXT, keys.REWARD): torch.randn(n, 1, generator=g),
                    (keys.NEXT, keys.DONE): done,
                    (keys.NEXT, keys.TERMINATED): done.clone(),
                    (keys.NEXT, keys.TRUNCATED): torch.zeros(n, 1, dtype=torch.bool),
                },
                batch_size=[n],
            )
        )
    return torch.cat(parts)


def _load(kind: str, root: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # skipped features: not what this property is about
        return (load_minari(root) if kind.startswith("minari") else load_lerobot(root)).rows


def _minari_arrow(root: Path) -> Path:
    """Written by the minari package itself (a test-only dependency)."""
    import minari
    from gymnasium import spaces
    from minari.data_collector.episode_buffer import EpisodeBuffer

    rng = np.random.default_rng(0)
    buffers = [
        EpisodeBuffer(
            id=e,
            observations=[rng.standard_normal(3).astype(np.float32) for _ in range(n + 1)],
            actions=[int(a) for a in rng.integers(0, 2, n)],
            rewards=list(rng.random(n)),
            terminations=[False] * (n - 1) + [True],
            truncations=[False] * n,
            infos={},
        )
        for e, n in enumerate([3, 4])
    ]
    path = tempfile.mkdtemp()
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = path
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            minari.create_dataset_from_buffers(
                "test/arrow-v0",
                buffers,
                observation_space=spaces.Box(-9, 9, (3,), np.float32),
                action_space=spaces.Discrete(2),
                data_format="arrow",
                algorithm_name="x",
            )
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before
    shutil.copytree(Path(path) / "test/arrow-v0", root)
    shutil.rmtree(path)
    return root


def _build(kind: str, root: Path) -> Path:
    if kind == "imitrl":
        return save_lerobot(_imitrl_rows(), root, fps=30)
    if kind == "lerobot v2.1":
        return write_v21(root, episodes_data([3, 2, 4]), chunks_size=2)
    if kind == "lerobot v3.0":
        return write_v30(root, episodes_data([3, 2, 4]), files=[(0, 0), (0, 0), (0, 1)])
    if kind == "minari hdf5":
        return _write(root, [_episode(3, 0), _episode(2, 1, truncated=True)])
    return _minari_arrow(root)


_PRISTINE: dict[str, tuple[Path, TensorDict]] = {}


def _pristine(kind: str) -> tuple[Path, TensorDict]:
    """The dataset, built once per session, and the rows it loads."""
    if kind not in _PRISTINE:
        root = _build(kind, Path(tempfile.mkdtemp()) / "ds")
        _PRISTINE[kind] = (root, _load(kind, root))
    return _PRISTINE[kind]


# -------------------------------------------------------------- corruptions
def _leaves(value, path=()):
    """Paths to every scalar/list leaf of parsed JSON (and of JSON held in a string)."""
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _leaves(v, (*path, k))]
    if isinstance(value, list) and value and isinstance(value[0], dict | list):
        return [p for i, v in enumerate(value) for p in _leaves(v, (*path, i))]
    if isinstance(value, str) and value.startswith("{"):
        try:
            inner = json.loads(value)
        except json.JSONDecodeError:
            return [path]
        return [path] + [(*path, ("json", p)) for p in _leaves(inner)]
    return [path]


def _get(value, path):
    for p in path:
        value = _get(json.loads(value), p[1]) if isinstance(p, tuple) else value[p]
    return value


def _replace(value, path, new):
    if not path:
        return new
    head, rest = path[0], path[1:]
    if isinstance(head, tuple):  # into JSON held in a string
        return json.dumps(_replace(json.loads(value), head[1], new))
    value[head] = _replace(value[head], rest, new)
    return value


def _near(old):
    """Values a corruption puts in place of ``old``: near misses and anything at all."""
    anything = st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-2, 2**40),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=4),
        st.lists(st.integers(-1, 9), max_size=3),
        st.just({}),
    )
    if isinstance(old, bool):
        return st.one_of(st.just(not old), anything)
    if isinstance(old, int):
        return st.one_of(st.sampled_from([old + 1, old - 1, 0, -old]), anything)
    if isinstance(old, str):
        return st.one_of(st.sampled_from(_DTYPES), anything)
    return anything


@st.composite
def corruptions(draw, kind: str):
    root, _ = _pristine(kind)
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    meta = [f for f in files if f.suffix in _JSON]
    op = draw(st.sampled_from(["truncate", "flip", "delete", "meta"]))
    if op == "flip" and kind in ("imitrl",):
        name = draw(st.sampled_from(files))
    else:
        name = draw(st.sampled_from(meta if op in ("flip", "meta") else files))
    size = (root / name).stat().st_size
    if op == "truncate":
        return op, name, draw(st.integers(0, max(size - 1, 0)))
    if op == "flip":
        return op, name, (draw(st.integers(0, size - 1)), draw(st.integers(0, 7)))
    if op == "delete":
        return op, name, None
    text = (root / name).read_text()
    lines = text.splitlines() if name.suffix == ".jsonl" else [text]
    line = draw(st.integers(0, len(lines) - 1))
    parsed = json.loads(lines[line])
    path = draw(st.sampled_from(_leaves(parsed)))
    return op, name, (line, path, draw(_near(_get(parsed, path))))


def _corrupt(root: Path, op: str, name: Path, arg) -> None:
    path = root / name
    if op == "truncate":
        path.write_bytes(path.read_bytes()[:arg])
    elif op == "flip":
        data = bytearray(path.read_bytes())
        data[arg[0]] ^= 1 << arg[1]
        path.write_bytes(bytes(data))
    elif op == "delete":
        path.unlink()
    else:
        line, leaf, new = arg
        lines = path.read_text().splitlines() if path.suffix == ".jsonl" else [path.read_text()]
        lines[line] = json.dumps(_replace(json.loads(lines[line]), leaf, new))
        path.write_text("\n".join(lines) + "\n")


def _same(a: TensorDict, b: TensorDict, exact_dtypes: bool) -> bool:
    if set(a.keys(True, True)) != set(b.keys(True, True)):
        return False
    for key in a.keys(True, True):
        x, y = a.get(key), b.get(key)
        if x.shape != y.shape or (exact_dtypes and x.dtype != y.dtype):
            return False
        if not torch.equal(x.double(), y.double()):
            return False
    return True


def _check(kind: str, corruption) -> None:
    pristine, rows = _pristine(kind)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        shutil.copytree(pristine, root)
        _corrupt(root, *corruption)
        try:
            loaded = _load(kind, root)
        except ValueError:
            event(f"{corruption[0]}: refused (ValueError)")
            return
        assert _same(rows, loaded, exact_dtypes=kind == "imitrl"), corruption
        event(f"{corruption[0]}: loaded identical rows")


# --------------------------------------------------------------------- tests
@SETTINGS
@given(corruption=corruptions("imitrl"))
def test_save_lerobot_datasets_load_identically_or_are_refused(corruption):
    _check("imitrl", corruption)


@SETTINGS
@given(corruption=corruptions("lerobot v2.1"))
def test_lerobot_v21_datasets_load_identically_or_are_refused(corruption):
    _check("lerobot v2.1", corruption)


@SETTINGS
@given(corruption=corruptions("lerobot v3.0"))
def test_lerobot_v30_datasets_load_identically_or_are_refused(corruption):
    _check("lerobot v3.0", corruption)


@SETTINGS
@given(corruption=corruptions("minari hdf5"))
def test_minari_hdf5_datasets_load_identically_or_are_refused(corruption):
    _check("minari hdf5", corruption)


@pytest.mark.skipif(importlib.util.find_spec("minari") is None, reason="needs minari")
@SETTINGS
@given(corruption=corruptions("minari arrow"))
def test_minari_arrow_datasets_load_identically_or_are_refused(corruption):
    _check("minari arrow", corruption)

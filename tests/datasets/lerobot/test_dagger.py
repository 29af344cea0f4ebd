"""DAgger rounds written in LeRobot's DAgger schema (``save_dagger_lerobot``, issue 48).

LeRobot's DAgger strategy tags corrections ``intervention`` (bool, shape ``(1,)``); imitrl
writes ``EXPERT_EXECUTED`` there and its rounds' provenance beside it. Checked: the columns
as LeRobot declares them, every row back (values, dtypes, rounds, flags), the beta and
policy version of each round, rows out of order refused before anything is written, and a
committed 5-round dataset an imitrl DAgger run wrote (``tests/fixtures/lerobot_dagger``)
loading with its counts intact and written again the same way today. Where lerobot itself
is installed, it loads that dataset and trains 10 steps on it.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.data.provenance import NO_BETA
from imitrl.datasets import load_lerobot, save_dagger_lerobot

FIXTURE = Path(__file__).resolve().parents[2] / "fixtures" / "lerobot_dagger"
DATA = "data/chunk-000/file-000.parquet"


def dagger_rows(rounds=(0, 1, 1, 2, 3), length=6, seed=0) -> TensorDict:
    """Episodes of ``length`` frames, one per entry of ``rounds``: round 0 all expert,
    later rounds a mixture of the expert's and the learner's frames."""
    g = torch.Generator().manual_seed(seed)
    n = len(rounds) * length
    episode = torch.arange(len(rounds)).repeat_interleave(length)
    rnd = torch.tensor(rounds).repeat_interleave(length)
    executed = torch.rand(n, generator=g) < 0.4
    executed[rnd == 0] = True
    label = torch.randn(n, 2, generator=g)
    own = torch.randn(n, 2, generator=g)
    return TensorDict(
        {
            keys.OBSERVATION: torch.randn(n, 3, generator=g),
            keys.EXPERT_ACTION: label,
            keys.ACTION: torch.where(executed[:, None], label, own),
            keys.EXPERT_EXECUTED: executed,
            keys.EPISODE: episode + 10,
            keys.ROUND: rnd,
            keys.STEP: torch.arange(length).repeat(len(rounds)),
        },
        batch_size=[n],
    )


def _load(root, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_lerobot(root, **kwargs)


def test_rounds_are_written_in_lerobots_dagger_schema_and_read_back(tmp_path):
    rows = dagger_rows()
    root = save_dagger_lerobot(rows, tmp_path / "ds", fps=10, betas={1: 0.25, 3: 0.0})
    features = json.loads((root / "meta/info.json").read_text())["features"]
    # LeRobot's DAgger strategy declares intervention exactly so (DAggerStrategyConfig)
    assert features["intervention"] == {"dtype": "bool", "shape": [1], "names": None}
    assert features["imitrl.beta"]["dtype"] == "float32"
    assert features["imitrl.policy_version"]["dtype"] == "int64"
    table = pq.read_table(root / DATA)  # what LeRobot's reader sees: plain parquet columns
    assert table.column("intervention").to_pylist() == rows[keys.EXPERT_EXECUTED].tolist()
    loaded = _load(root).rows
    for key in rows.keys():
        assert torch.equal(loaded[key], rows[key]), key
    beta, version = loaded[keys.BETA], loaded[keys.POLICY_VERSION]
    rnd = rows[keys.ROUND]
    assert beta[rnd == 0].eq(1.0).all()  # demonstrations: the expert always acted
    assert beta[rnd == 1].eq(0.25).all() and beta[rnd == 3].eq(0.0).all()
    assert beta[rnd == 2].eq(NO_BETA).all()  # not given and not all the expert's: unknown
    assert torch.equal(version, (rnd - 1).clamp_min(-1))


def test_rows_that_carry_their_provenance_keep_it(tmp_path):
    rows = dagger_rows()
    rows.set(keys.BETA, torch.full((rows.shape[0],), 0.5))
    rows.set(keys.POLICY_VERSION, torch.full((rows.shape[0],), 7))
    loaded = _load(save_dagger_lerobot(rows, tmp_path / "ds", fps=10, betas={1: 0.9})).rows
    assert loaded[keys.BETA].eq(0.5).all() and loaded[keys.POLICY_VERSION].eq(7).all()


@pytest.mark.parametrize(
    "edit, said",
    [
        (lambda r: r[keys.ROUND].__setitem__(slice(24, 30), 1), r"row 24 \(episode 14\): round 1 after round 2"),
        (lambda r: r[keys.ROUND].__setitem__(8, 2), r"row 8 \(episode 11\): round 2 after round 1"),
    ],
)  # fmt: skip
def test_rounds_out_of_order_are_refused_before_anything_is_written(tmp_path, edit, said):
    rows = dagger_rows()
    edit(rows)
    with pytest.raises(ValueError, match=said):
        save_dagger_lerobot(rows, tmp_path / "ds", fps=10)
    assert not (tmp_path / "ds").exists()


def test_the_committed_dagger_dataset_loads_with_its_counts_and_is_written_the_same(tmp_path):
    expected = json.loads((FIXTURE / "expected.json").read_text())
    loaded = _load(FIXTURE / "lerobot")
    rows = loaded.rows
    rnd, flags = rows[keys.ROUND], rows[keys.EXPERT_EXECUTED]
    counts = {
        str(r): [int((rnd == r).sum()), int(flags[rnd == r].sum())] for r in rnd.unique().tolist()
    }
    assert counts == expected["frames_and_interventions_per_round"]
    assert len(counts) == 5 and loaded.num_episodes == expected["episodes"]
    betas = {str(r): float(rows[keys.BETA][rnd == r][0]) for r in rnd.unique().tolist()}
    assert betas == expected["betas"]
    # today's writer writes the same features and rows from the same rows
    again = save_dagger_lerobot(rows, tmp_path / "again", fps=loaded.fps, tasks=loaded.tasks)
    info = json.loads((again / "meta/info.json").read_text())
    assert info["features"] == loaded.metadata["features"]
    back = _load(again).rows
    for key in rows.keys(True, True):
        assert torch.equal(back[key], rows[key]), key


def test_lerobot_loads_the_committed_dataset_and_trains_ten_steps():
    pytest.importorskip("lerobot.datasets")  # lerobot with its dataset extra (0.6.1 checked)
    try:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset
    except ImportError:  # pragma: no cover - later lerobot layouts
        from lerobot.datasets import LeRobotDataset
    expected = json.loads((FIXTURE / "expected.json").read_text())
    dataset = LeRobotDataset("imitrl/dagger_fixture", root=FIXTURE / "lerobot")
    assert dataset.meta.total_episodes == expected["episodes"]
    interventions = torch.as_tensor(dataset.hf_dataset["intervention"]).bool().sum()
    total = sum(v[1] for v in expected["frames_and_interventions_per_round"].values())
    assert int(interventions) == total
    torch.manual_seed(0)
    state_dim = dataset.meta.features["observation.state"]["shape"][0]
    action_dim = dataset.meta.features["action"]["shape"][0]
    net = torch.nn.Sequential(
        torch.nn.Linear(state_dim, 32), torch.nn.ReLU(), torch.nn.Linear(32, action_dim)
    )
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    loader = torch.utils.data.DataLoader(dataset, batch_size=32, shuffle=True)
    losses: list[float] = []
    while len(losses) < 10:  # epochs of 200 frames, 32 at a time
        for batch in loader:
            weight = 1.0 + batch["intervention"].float().reshape(-1, 1)  # corrections twice
            loss = (weight * (net(batch["observation.state"]) - batch["action"]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
            if len(losses) == 10:
                break
    assert len(losses) == 10 and all(math.isfinite(v) for v in losses)

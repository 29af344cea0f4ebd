"""LeadSource (issue 45): on two gloo ranks rank 0's source plays each round and every
rank gets its rows; the other rank's source is checked against, never played; a
checkpoint's state is rank 0's to restore."""

from __future__ import annotations

import pytest
import torch
import torch.multiprocessing as mp
from tensordict import TensorDict

from tests import _child


class _Played:
    """Rank 0's source: rows that name the round."""

    def __init__(self) -> None:
        self.checked, self.loaded = 0, []

    def check(self, expert, learner) -> None:
        self.checked += 1

    def state_dict(self) -> dict:
        return {"seed": 7}

    def load_state_dict(self, state: dict) -> None:
        self.loaded.append(state)

    def collect(self, behaviour, num_episodes, *, round_index, first_episode) -> TensorDict:
        n = 3 * num_episodes
        return TensorDict(
            {"round": torch.full((n,), round_index), "episode": torch.arange(n) + first_episode},
            batch_size=[n],
        )


class _NeverPlayed(_Played):
    """Another rank's source: playing it is the bug."""

    def collect(self, *args, **kwargs):
        raise AssertionError("a rank > 0 played a round")

    def load_state_dict(self, state: dict) -> None:
        raise AssertionError("a rank > 0 restored a source state")


def _rank(rank: int, world: int, init: str, out: str) -> None:
    import torch.distributed as dist

    from imitrl.algorithms.lead_source import LeadSource

    dist.init_process_group("gloo", init_method=f"file://{init}", rank=rank, world_size=world)
    try:
        inner = _Played() if rank == 0 else _NeverPlayed()
        source = LeadSource(inner)
        source.check(None, None)
        source.load_state_dict({"seed": 7})
        rounds = [source.collect(None, k + 1, round_index=k, first_episode=10 * k) for k in (1, 2)]
        torch.save({"rounds": rounds, "checked": inner.checked, "loaded": inner.loaded},
                   f"{out}.{rank}")  # fmt: skip
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def ranks(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lead")
    out = str(folder / "out")
    mp.start_processes(
        _rank,
        args=(2, str(folder / "init"), out),
        nprocs=2,
        join=True,
        start_method=_child.forkserver(),
    )
    return [torch.load(f"{out}.{r}", weights_only=False) for r in range(2)]


def test_every_rank_gets_rank_0s_rows_and_checks_its_own_source(ranks):
    lead, other = ranks
    assert [r.shape[0] for r in lead["rounds"]] == [6, 9]
    for a, b in zip(lead["rounds"], other["rounds"]):
        assert (a == b).all()
    assert lead["rounds"][1]["round"].unique().tolist() == [2]
    assert lead["checked"] == other["checked"] == 1
    assert lead["loaded"] == [{"seed": 7}] and other["loaded"] == []


def test_in_one_process_it_is_the_source_itself():
    from imitrl.algorithms.lead_source import LeadSource

    rows = LeadSource(_Played()).collect(None, 2, round_index=0, first_episode=0)
    assert rows.shape[0] == 6

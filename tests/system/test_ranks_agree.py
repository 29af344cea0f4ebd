"""What data-parallel ranks must hold alike, checked on two real gloo ranks (a hostile
review: a resumed ``--nproc 2`` DAgger run trained rank 0 from its checkpoint and rank 1
from scratch, all-reducing gradients of different rounds, and published the result; ranks
of two machines trained on different datasets without a word)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import torch
import torch.multiprocessing as mp

from tests import _child


def _rank(rank: int, world: int, init: str, folder: str) -> None:
    import torch.distributed as dist

    from imitrl.algorithms.dagger import _same_round_on_every_rank
    from imitrl.jobs.configs import DAggerJob
    from imitrl.jobs.ranks import rows_digest, run_folder
    from imitrl.system.ranks import check_same

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init}", rank=rank, world_size=world)
    said: dict = {}
    try:
        check_same(3, "counts")  # alike: nothing
        for name, call in (
            ("value", lambda: check_same(rank, "values")),
            ("round", lambda: _same_round_on_every_rank(2 + rank)),
        ):
            try:
                call()
                said[name] = None
            except ValueError as err:
                said[name] = str(err)
        from tensordict import TensorDict

        rows = TensorDict({"observation": torch.arange(6.0).reshape(3, 2)}, [3])
        said["digest_same"] = rows_digest(rows) == rows_digest(rows.clone())
        rows["observation"][2, 1] = 7.0
        said["digest_moves"] = rows_digest(rows) != rows_digest(rows.clone().zero_())
        # --resume: every rank starts from the checkpoint rank 0 continues (its staging
        # folder's, as a killed run left it), not from --out's
        config = replace(DAggerJob(), out=Path(folder) / "out", resume=True)
        with run_folder(config, resume=True) as where:
            said["resumed"] = (where / "run" / "state.json").read_text()
    finally:
        dist.destroy_process_group()
    Path(folder, f"rank{rank}.json").write_text(json.dumps(said))


def test_ranks_refuse_what_they_do_not_hold_alike_and_resume_rank_0s_checkpoint(tmp_path):
    from imitrl.fs.run_folder import staging_folder

    killed = staging_folder(tmp_path / "out") / "run"
    killed.mkdir(parents=True)
    (killed / "state.json").write_text('{"next_round": 2}')
    mp.start_processes(_rank, args=(2, str(tmp_path / "init"), str(tmp_path)), nprocs=2,
                       join=True, start_method=_child.forkserver())  # fmt: skip
    zero, one = (json.loads((tmp_path / f"rank{r}.json").read_text()) for r in (0, 1))
    assert zero["value"] is None and zero["round"] is None  # rank 0 is the reference
    assert one["value"] == (
        "rank 1's values differ from rank 0's (1 against 0): every rank must hold the same"
    )
    assert one["round"].startswith("rank 1 resumed at round 3, rank 0 at round 2")
    assert zero["digest_same"] and one["digest_moves"]
    assert zero["resumed"] == one["resumed"] == '{"next_round": 2}'

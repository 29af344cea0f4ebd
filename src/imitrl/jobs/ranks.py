"""Where a job's rank writes and what the ranks of a ``--nproc`` run must hold alike.

Rank 0 alone claims ``--out`` (:func:`run_folder`), evaluates and reports
(:func:`evaluating`, :func:`lead`); the other ranks write into scratch folders nothing
keeps, resume the checkpoint rank 0 continues, and hold the demonstrations rank 0 holds
(:func:`rows_digest`, compared by :func:`imitrl.system.ranks.check_same`). In a single
process every function here is the plain case.
"""

from __future__ import annotations

import contextlib
import hashlib
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import TypeVar

import torch
from tensordict import TensorDictBase

from imitrl.fs.run_folder import claimed
from imitrl.jobs.configs import BCJob, GAILJob
from imitrl.system.ranks import barrier, from_lead, rank_and_world

__all__ = ["RUN_CHECKPOINT", "evaluating", "lead", "rows_digest", "run_folder"]

JobT = TypeVar("JobT", bound=BCJob | GAILJob)
RUN_CHECKPOINT = "run"
"""the folder of ``--out`` where ``imitrl dagger`` keeps its resumable checkpoint"""


@contextlib.contextmanager
def run_folder(config: BCJob | GAILJob, *, resume: bool = False) -> Iterator[Path]:
    """Where the run writes: ``--out`` claimed (:func:`imitrl.fs.run_folder.claimed`'s
    rule); on a data-parallel rank other than 0 (``--nproc``) a scratch folder that
    nothing keeps: rank 0 alone writes ``--out`` (``resume``: the scratch starts with a
    copy of the DAgger checkpoint rank 0 continues, :data:`RUN_CHECKPOINT` of its staging
    folder, which rank 0 names to the others: every rank resumes the same round)."""
    if rank_and_world()[0] == 0:
        with claimed(config.out, overwrite=config.overwrite, resume=resume) as folder:
            if resume:  # the checkpoint rank 0 continues: its staged copy, or the unfinished run's
                own = folder / RUN_CHECKPOINT
                from_lead(str(own) if own.is_dir() else None)
                barrier()  # the other ranks have copied it before anything writes it
            yield folder
    else:
        with tempfile.TemporaryDirectory(prefix="imitrl-rank-") as scratch:
            if resume:
                saved = from_lead(None)  # where rank 0 resumes (a file system they share)
                if saved is not None and not Path(saved).is_dir():
                    raise ValueError(
                        f"rank {rank_and_world()[0]} cannot read rank 0's checkpoint {saved}: "
                        "--resume on ranks of several machines needs --out on a file system "
                        "they share"
                    )
                if saved is not None:
                    shutil.copytree(saved, Path(scratch) / RUN_CHECKPOINT, symlinks=True)
                barrier()
            yield Path(scratch)


def lead(config: JobT) -> JobT:
    """``config`` as this rank runs it: rank 0 as given; another rank (``--nproc``)
    without progress bars (one per run) and without evaluations (:func:`evaluating`)."""
    return config if rank_and_world()[0] == 0 else replace(config, progress=False)


def evaluating() -> bool:
    """Whether this process evaluates and reports: rank 0 (every rank plays the same
    episodes and fits its share; the evaluations are rank 0's alone)."""
    return rank_and_world()[0] == 0


def rows_digest(rows: TensorDictBase) -> tuple[int, str]:
    """``(rows, sha256 of every entry's name, dtype, shape and bytes)``: what tells two
    ranks' demonstrations apart (a dataset another machine holds otherwise)."""
    if rank_and_world()[1] == 1:
        return len(rows), ""  # nothing to compare with
    digest = hashlib.sha256()
    for key, value in sorted(rows.items(include_nested=True, leaves_only=True), key=str):
        if not isinstance(value, torch.Tensor):  # a string entry (a task's text)
            digest.update(f"{key}{value!r}".encode())
            continue
        tensor = value.detach().cpu().contiguous()
        digest.update(f"{key}{tensor.dtype}{tuple(tensor.shape)}".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return len(rows), digest.hexdigest()[:16]

"""``--nproc N``: a training command in N data-parallel ranks, launched as ``torchrun``
launches them (torch's elastic launcher, ``torch.distributed.launcher.api``).

:func:`launch` starts N processes on this machine, each running
``python -m imitrl`` with the command line it was given (as torchrun starts a script):
a rank joins the process group (:func:`process_group`, from the environment the
launcher sets: gloo on CPUs, NCCL on GPUs) and runs the command
as one rank (:mod:`imitrl.system.ranks`: every rank plays the same episodes and fits its
share of every batch; rank 0 alone writes ``--out``, evaluates and reports). A rank that
dies takes the others down with it (the launcher stops them; ``max_restarts=0``), and the
command ends with one line naming it. On a cluster, start the same command under
``torchrun --nnodes ... --nproc-per-node ...`` instead: it finds ``RANK`` set and runs as
that rank (``--nproc`` is then each node's count, read by torchrun, not by imitrl).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import uuid
from collections.abc import Iterator, Sequence

__all__ = ["RankLostError", "in_rank", "launch", "process_group", "quiet"]


def in_rank() -> bool:
    """Whether this process was started as a rank (``torchrun`` or :func:`launch`)."""
    return "RANK" in os.environ and "WORLD_SIZE" in os.environ


def launch(nproc: int, argv: Sequence[str]) -> int:
    """Run ``python -m imitrl argv`` in ``nproc`` ranks on this machine (what ``torchrun
    --standalone --nproc-per-node N -m imitrl argv`` runs); 0 when every rank finished,
    else the exit status of a rank that refused its input (2, its line printed by rank 0).

    Raises:
        RankLostError: a rank died (killed, or an uncaught error), naming it.
    """
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.launcher.api import LaunchConfig, elastic_launch

    config = LaunchConfig(
        min_nodes=1,
        max_nodes=1,
        nproc_per_node=int(nproc),
        run_id=f"imitrl-{uuid.uuid4().hex[:8]}",
        rdzv_backend="c10d",  # torchrun --standalone's rendezvous: a free local port
        rdzv_endpoint="localhost:0",
        max_restarts=0,  # a lost rank ends the run: the others are stopped, not restarted
        monitor_interval=0.5,
    )
    # the launcher logs a lost rank's traceback at ERROR; the command's one line says it
    logging.getLogger("torch.distributed.elastic").setLevel(logging.CRITICAL)
    try:
        elastic_launch(config, sys.executable)("-m", "imitrl", *argv)
    except ChildFailedError as err:
        codes = {failure.exitcode for failure in err.failures.values()}
        if codes == {2}:  # bad input found by the ranks (a dataset for another env)
            return 2
        lost = ", ".join(
            f"rank {rank} ({_how(failure.exitcode)})" for rank, failure in err.failures.items()
        )
        raise RankLostError(f"{lost} ended the run; the other ranks were stopped") from None
    return 0


class RankLostError(RuntimeError):
    """A rank of a ``--nproc`` run died (killed, or an error it did not report)."""


def _how(exitcode: int) -> str:
    """``-9`` -> ``"killed by SIGKILL"``, ``1`` -> ``"exit status 1"``."""
    if exitcode < 0:
        import signal

        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit status {exitcode}"


@contextlib.contextmanager
def process_group(backend: str) -> Iterator[None]:
    """Within: this rank in the default process group on ``backend`` (``"gloo"``,
    ``"nccl"``: the rank's own GPU, ``LOCAL_RANK``), from the environment the launcher
    set (``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``, ``MASTER_PORT``)."""
    import torch
    import torch.distributed as dist

    if backend == "nccl":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    dist.init_process_group(backend)
    try:
        yield
    finally:
        dist.destroy_process_group()


def quiet() -> bool:
    """Whether this process is a rank other than 0: only rank 0 reports and names errors."""
    return in_rank() and os.environ.get("RANK") != "0"

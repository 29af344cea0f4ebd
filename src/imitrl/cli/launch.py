"""``--nproc N``: a training command in N data-parallel ranks, launched as ``torchrun``
launches them (torch's elastic launcher, ``torch.distributed.launcher.api``).

:func:`launch` starts N processes on this machine, each running
``python -m imitrl`` with the command line it was given (as torchrun starts a script):
a rank joins the process group (:func:`process_group`, from the environment the
launcher sets: gloo on CPUs, NCCL on GPUs) and runs the command
as one rank (:mod:`imitrl.system.ranks`: every rank plays the same episodes and fits its
share of every batch; rank 0 alone writes ``--out``, evaluates and reports). A rank that
dies takes the others down with it (the launcher stops them; ``max_restarts=0``), and the
command ends with one line naming it; a launcher killed outright takes its ranks with it
(each watches its parent). On a cluster, start the same command under
``torchrun --nnodes ... --nproc-per-node ...`` instead: it finds ``RANK`` set and runs as
that rank (``--nproc`` is then each node's count, read by torchrun, not by imitrl).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import time
import uuid
from collections.abc import Iterator, Sequence

__all__ = ["PEER_LOST", "RankLostError", "in_rank", "launch", "peer_lost", "process_group", "quiet"]


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
        rank, exitcode = _lost(err)
        raise RankLostError(
            f"rank {rank} ({_how(exitcode)}) ended the run; the other ranks were stopped"
        ) from None
    return 0


def _lost(err) -> tuple[int, int]:
    """The rank a failed run lost first, and its exit code: one killed by a signal other
    than the launcher's SIGTERM (its peers then fail for want of it, or are stopped),
    else the earliest failure."""
    killed = [
        (rank, f.exitcode)
        for rank, f in sorted(err.failures.items())
        if f.exitcode < 0 and f.exitcode != -signal.SIGTERM
    ]
    if killed:
        return killed[0]
    rank, first = err.get_first_failure()
    return rank, first.exitcode


class RankLostError(RuntimeError):
    """A rank of a ``--nproc`` run died (killed, or an error it did not report)."""


def _how(exitcode: int) -> str:
    """``-9`` -> ``"killed by SIGKILL"``, ``1`` -> ``"exit status 1"``."""
    if exitcode < 0:
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
    _end_with_launcher()
    dist.init_process_group(backend)
    try:
        yield
    finally:
        dist.destroy_process_group()


LAUNCHER_POLL_S = 1.0
"""how often a rank looks whether its launcher is still there"""


def _end_with_launcher() -> None:
    """End this rank when the process that launched it is gone (killed outright, it
    cannot stop its ranks; they would fit on alone, holding the cores): a daemon thread
    compares the parent's pid every :data:`LAUNCHER_POLL_S` seconds."""
    import threading

    launcher = os.getppid()

    def watch() -> None:
        while os.getppid() == launcher:
            time.sleep(LAUNCHER_POLL_S)
        print(f"imitrl: rank {os.environ.get('RANK')}: the launcher is gone", file=sys.stderr)
        os.kill(os.getpid(), signal.SIGTERM)  # the whole process, whatever thread it is in

    threading.Thread(target=watch, name="imitrl-launcher-watch", daemon=True).start()


PEER_LOST = ("Connection closed by peer", "Connection reset by peer", "Broken pipe",
             "Socket Timeout", "timed out", "Connection refused")  # fmt: skip
"""what a collective's error says when another rank is gone (gloo, NCCL, the store)"""


def peer_lost(err: RuntimeError) -> bool:
    """Whether ``err`` is a collective's failure for want of another rank (not a bug of
    this rank's own, which keeps its traceback)."""
    import torch.distributed as dist

    return isinstance(err, dist.DistError) or any(s in str(err) for s in PEER_LOST)


def quiet() -> bool:
    """Whether this process is a rank other than 0: only rank 0 reports and names errors."""
    return in_rank() and os.environ.get("RANK") != "0"

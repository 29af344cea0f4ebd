"""Peak anonymous memory of a streamed load into a disk buffer, in a fresh process (the
LeRobot and Minari memory tests)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

_SCRIPT = r"""
import sys, threading, time, torch
sys.path[:0] = sys.argv[3:]
torch.set_num_threads(1)
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import {loader} as load
from imitrl.datasets.{package} import _stream
_stream.PIECE_ROWS = 4096

def anon():  # the process's own memory; the buffer's mapped files are page cache
    fields = dict(line.split(":", 1) for line in open("/proc/self/status"))
    return int(fields["RssAnon"].split()[0]) << 10

peak, done = [0], threading.Event()
def sample():
    while not done.is_set():
        peak[0] = max(peak[0], anon())
        time.sleep(0.002)

buf = DemonstrationBuffer(path=sys.argv[2])
before = anon()
sampler = threading.Thread(target=sample)
sampler.start()
load(sys.argv[1], into=buf)
done.set()
sampler.join()
print(len(buf), max(peak[0], anon()) - before)
"""


def streamed_load_peak(package: str, root: Path, buffer: Path) -> tuple[int, int]:
    """``(rows loaded, peak RssAnon growth in bytes)`` of ``load_<package>(root,
    into=DemonstrationBuffer(path=buffer))`` (pieces of 4096 rows; RssAnon sampled every
    2 ms) in a fresh process."""
    script = textwrap.dedent(_SCRIPT).format(loader=f"load_{package}", package=package)
    src = next(p for p in sys.path if (Path(p) / "imitrl").is_dir())
    # a fresh interpreter: its resident set is its own (a fork shares the server's pages)
    done = subprocess.run(
        [sys.executable, "-c", script, str(root), str(buffer), src],
        capture_output=True,
        text=True,
        check=True,
    )
    count, grew = map(int, done.stdout.split()[-2:])
    return count, grew

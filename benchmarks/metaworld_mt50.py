"""Meta-World MT50 from state: DAgger with the scripted experts, BC beside it at equal labels.

All 50 v3 tasks of Meta-World (``imitrl.envs.metaworld``: ``metaworld/<task>-v3``, a new
goal and object placement every episode, drawn from the seed), each with its scripted
policy as the queryable expert, one cell of ``loss_functions.py``'s machinery per (task,
loss, seed), as ``metaworld_mt10.py`` runs MT10 (``_metaworld_suite.py``): BC on the
demonstrations, DAgger's relabel rounds on top of them, and BC given as many expert
labels as DAgger's last fit saw. Success is Meta-World's (``info["success"]`` at any
step), per task with a Wilson interval over the seeds' pooled episodes, the expert's
beside it on the same held-out starts; across tasks the expert-normalised IQM with
stratified bootstrap intervals. The target (issue 46): DAgger reaches >= 0.95 of the
expert's success on at least 45 of the 50 tasks from at most 10 demonstrations.

Runnable in parts (``--tasks``, ``--first-seed``) and merged (``--merge``): a cell's
digits depend on its seed alone.

    python benchmarks/metaworld_mt50.py --jobs 2     # full run, refreshes benchmarks/README.md
    python benchmarks/metaworld_mt50.py --quick      # smoke run, into a temporary directory
    python benchmarks/metaworld_mt50.py --tasks assembly-v3 hammer-v3 --out /tmp/part1
    python benchmarks/metaworld_mt50.py --merge /tmp/part1/metaworld_mt50.json \\
        /tmp/part2/metaworld_mt50.json --demos 10    # one report of the parts
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _metaworld_suite
from _loss_functions.tasks import LearnerSettings
from _metaworld_suite import Suite
from imitrl.envs.metaworld import MT50
from metaworld_mt10 import PROTOCOL as MT10_PROTOCOL

NAME = "metaworld_mt50"
PROTOCOL = replace(
    MT10_PROTOCOL,
    demo_episodes=10,
    max_episode_steps=None,
    beta_decay=0.5,
    bc=replace(MT10_PROTOCOL.bc, num_steps=2000),
    round_steps=1000,
    learner=LearnerSettings(hidden=(256, 256), lr=1e-3),
    eval_episodes=10,
)
"""``metaworld_mt10.py``'s DAgger (2 relabel rounds x 3 episodes, warm-started) with five
changes, the last three measured:

* 10 demonstrations, the most the target allows;
* episodes at Meta-World's own 500-step limit, not cut at 150: the experts' success is
  their own (peg-insert-side's is 0.92 at 500 steps and 0.72 at 150 over MT10's 25
  held-out starts);
* 10 held-out episodes a seed (30 a task): with 15, 0.95 of an expert at 15/15 is
  15/15, so a single failed episode fails the task;
* Ross et al.'s beta schedule (the expert drives relabel round 1, a fair coin round 2):
  with beta 0, a learner that comes down off its mark near an object is told to go back up
  by the scripted expert, and those retreats fill DAgger's rows, the more so the longer
  its episodes run (``dagger_labels.py`` measures both on MT10: its README section);
* a 256-256 MLP at lr 1e-3, fits of 2000 steps x 256 and 1000 a relabel round, not MT10's
  128-128 at lr 3e-3 for 320 and 160: at MT10's budget DAgger reached the target on 20
  of the 50 tasks, and on five of the short ones (3 seeds, 15 episodes) this budget
  lifted it from 2 to 10 successes on assembly, 1 to 7 on stick-pull, 3 to 8 on
  pick-out-of-hole, 8 to 10 on hand-insert and 9 to 10 on push-wall. Four relabel rounds
  instead of two (the schedule's betas 1, 0.5, 0.25, 0.125) did worse on ten short tasks
  (basketball 0 of 15 against BC at its queries' 11, hand-insert 6 against 15): more of
  the learner's own states, more of the expert's retreats (the README's MT50 reading)."""

MT50_SUITE = Suite(NAME, "MT50", MT50, PROTOCOL, losses=("mse",), demos=(10,), seeds=3)


def main(argv: list[str] | None = None) -> None:
    _metaworld_suite.main(MT50_SUITE, __doc__, argv)


if __name__ == "__main__":
    main()

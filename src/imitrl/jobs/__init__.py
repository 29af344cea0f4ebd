"""Jobs: what each ``imitrl`` command runs, as plain functions of one frozen config.

``run_bc(BCJob(...))``, ``run_dagger(DAggerJob(...))``, ``run_eval(EvalJob(...))`` and
``run_bench(BenchJob(...))`` return a dict (what ``results.json`` holds) and raise
``ValueError`` on bad input; the CLI (:mod:`imitrl.cli`) builds the config from the
flags, one flag per field. Tests and benchmarks call the functions directly.
"""

from imitrl.jobs.bc import BCJob, run_bc
from imitrl.jobs.bench import BenchJob, run_bench
from imitrl.jobs.dagger import DAggerJob, run_dagger
from imitrl.jobs.evaluate import EvalJob, run_eval

__all__ = [
    "BCJob",
    "BenchJob",
    "DAggerJob",
    "EvalJob",
    "run_bc",
    "run_bench",
    "run_dagger",
    "run_eval",
]

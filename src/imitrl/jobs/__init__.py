"""Jobs: what each ``imitrl`` command runs, as plain functions of one frozen config.

``run_bc(BCJob(...))``, ``run_dagger(DAggerJob(...))``, ``run_eval(EvalJob(...))`` and
``run_bench(BenchJob(...))`` return a dict (what ``results.json`` holds) and raise
``ValueError`` on bad input; the CLI (:mod:`imitrl.cli`) builds the config from the
flags, one flag per field. Tests and benchmarks call the functions directly.
``load_learner(run_folder, env)`` rebuilds a run's saved learner for ``env`` and loads its
weights (what ``imitrl eval --checkpoint`` evaluates); ``read_checkpoint(run_folder)``
reads its config and weights, checked, without building anything.

Each name is imported from its module on first use (PEP 562), so that ``imitrl bench``
and ``imitrl eval --help`` do not import what ``imitrl bc`` needs.
"""

from imitrl import _lazy_exports

__all__ = [
    "BCJob",
    "BenchJob",
    "DAggerJob",
    "EvalJob",
    "load_learner",
    "read_checkpoint",
    "run_bc",
    "run_bench",
    "run_dagger",
    "run_eval",
]

__getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "BCJob": "imitrl.jobs.configs",
        "run_bc": "imitrl.jobs.bc",
        "BenchJob": "imitrl.jobs.bench",
        "run_bench": "imitrl.jobs.bench",
        "DAggerJob": "imitrl.jobs.configs",
        "run_dagger": "imitrl.jobs.dagger",
        "EvalJob": "imitrl.jobs.evaluate",
        "run_eval": "imitrl.jobs.evaluate",
        "load_learner": "imitrl.jobs.checkpoint",
        "read_checkpoint": "imitrl.jobs.checkpoint",
    },
)

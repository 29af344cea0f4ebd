"""Import cost: ``import imitrl`` and the command line's help start without torch.

Each check runs a fresh interpreter with ``-X importtime`` and reads from its stderr
every module the command imported. The help of ``bc``/``dagger``/``gail``/``airl`` lists
the registered losses and experts from :mod:`imitrl.jobs.names`, which a test here holds
equal to the registry and the experts themselves.
"""

from __future__ import annotations

import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import imitrl

HEAVY = ("torch", "torchrl", "tensordict", "sympy", "matplotlib", "ray")
"""top-level packages that the light entry points must not import"""


def imported(*args: str) -> tuple[subprocess.CompletedProcess, set[str]]:
    """Run ``python -X importtime *args``; (the process, every module it imported)."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", *args], capture_output=True, text=True, timeout=300
    )
    modules = {
        line.rsplit("|", 1)[1].strip()
        for line in proc.stderr.splitlines()
        if line.startswith("import time:") and "|" in line
    }
    return proc, modules


def heavy(modules: set[str]) -> list[str]:
    return sorted({m.split(".")[0] for m in modules} & set(HEAVY))


def test_import_imitrl_imports_nothing_heavy():
    proc, modules = imported("-c", "import imitrl")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "imitrl" in modules  # the measurement sees the import
    assert heavy(modules) == []
    assert not any(m.startswith("imitrl.") for m in modules)  # no subpackage either


@pytest.mark.parametrize(
    "argv",
    [[], ["eval"], ["bench"], ["frozenlake"], ["bc"], ["dagger"], ["gail"], ["airl"]],
    ids=["top", "eval", "bench", "frozenlake", "bc", "dagger", "gail", "airl"],
)
def test_help_imports_no_torch(argv):
    proc, modules = imported("-m", "imitrl", *argv, "--help")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "usage: imitrl" in proc.stdout
    assert heavy(modules) == []


def test_bench_runs_a_script_without_importing_torch():
    proc, modules = imported("-m", "imitrl", "bench", "no_such_benchmark")
    assert proc.returncode == 2  # run_bench refused the name: the job ran
    assert "unknown benchmark 'no_such_benchmark'" in proc.stderr
    assert heavy(modules) == []


def test_running_bc_imports_torch_so_the_checks_above_can_fail():
    """What the help avoids: the job's own module imports torch and TorchRL."""
    proc, modules = imported("-c", "import imitrl.jobs.bc")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert {"torch", "torchrl", "tensordict"} <= set(heavy(modules))
    help_proc, _ = imported("-m", "imitrl", "bc", "--help")
    assert "cross_entropy" in help_proc.stdout and "acrobot (Acrobot-v1)" in help_proc.stdout


def test_submodules_are_attributes_on_first_access():
    code = (
        "import sys, imitrl; assert 'imitrl.tabular' not in sys.modules; "
        "f = imitrl.tabular.value_iteration; assert 'algorithms' in dir(imitrl); "
        "assert not hasattr(imitrl, 'no_such_module')"
    )
    proc, _ = imported("-c", code)
    assert proc.returncode == 0, proc.stderr[-2000:]


def _packages(path: list[str] = imitrl.__path__, prefix: str = "imitrl.") -> list[str]:
    """Every public package of imitrl, found on disk (nothing is imported)."""
    names = []
    for m in pkgutil.iter_modules(path, prefix):
        if m.ispkg and not m.name.rsplit(".", 1)[1].startswith("_"):
            names.append(m.name)
            names += _packages(
                [str(Path(m.module_finder.path, m.name.rsplit(".", 1)[1]))], m.name + "."
            )
    return names


@pytest.mark.parametrize("name", _packages())
def test_every_exported_name_resolves(name):
    package = pytest.importorskip(name)  # the datasets need their extra
    exported = getattr(package, "__all__", [])
    for attr in exported:
        assert getattr(package, attr) is not None, f"{name}.{attr}"
    assert set(exported) <= set(dir(package))
    namespace: dict = {}
    exec(f"from {name} import *", namespace)
    assert set(exported) <= set(namespace)


def test_lazy_names_are_the_defining_modules_objects():
    from imitrl import jobs
    from imitrl.experiments import frozenlake
    from imitrl.experiments.frozenlake import config, study
    from imitrl.jobs import bc, bench, dagger, evaluate

    assert (jobs.BCJob, jobs.run_bc, jobs.DAggerJob) == (bc.BCJob, bc.run_bc, dagger.DAggerJob)
    assert (jobs.EvalJob, jobs.run_bench) == (evaluate.EvalJob, bench.run_bench)
    assert frozenlake.StudyConfig is config.StudyConfig and frozenlake.run_study is study.run_study
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        _ = jobs.nope


def test_the_names_help_lists_are_the_registrys_and_the_experts():
    from imitrl.jobs import names, resolve
    from imitrl.learners import registry

    assert names.LOSSES == tuple((e.name, e.actions, e.summary) for e in registry.entries())
    assert list(names.EXPERT_ENVS) == list(resolve.EXPERTS)
    for name, env_id in names.EXPERT_ENVS.items():  # each built-in expert acts in its env
        if env_id.startswith(("Inverted",)):
            continue  # MuJoCo: covered by tests/experts/test_experts.py
        from imitrl.envs import make_env

        env = make_env(env_id, seed=0)
        resolve.check_expert_fits(resolve.EXPERTS[name](), name, env_id, env)
        env.close()

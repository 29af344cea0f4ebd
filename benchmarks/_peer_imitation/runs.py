"""Launching ``peer_imitation.py``'s children: the expert check, the timed runs, the
peer's package versions. Every timed run is a whole fresh process; the parent measures
its wall time from launch to exit, the child reports its phases in a JSON file."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from tensordict import TensorDict

import _report
from _peer_imitation.imitrl_run import EXPERTS
from _peer_imitation.tasks import Task
from imitrl import keys

HERE = Path(__file__).resolve().parent
IMITRL_RUN, PEER_RUN = HERE / "imitrl_run.py", HERE / "peer_run.py"
LIBRARIES = ("imitrl", "imitation")
PLAN = (
    ("imitrl", "own", "plain"),
    ("imitation", "own", "plain"),
    ("imitrl", "matched", "plain"),
    ("imitation", "matched", "plain"),
    ("imitrl", "own", "collector_trick"),
)
"""(library, protocol, process) of one (task, seed), in the order they run, each a fresh
process: imitrl's children plain scripts (as a user runs imitrl from Python) beside
imitation's under both protocols, then imitrl ``own`` with the ``imitrl`` command's
collector trick, a row of its own (``tasks.PROCESSES``)"""
QUICK_WORKERS = 8
"""processes at once in a ``--quick`` run (the smoke run: timings moot)"""
PEER_ENV = "IMITRL_PEER_PYTHON"
"""the environment variable naming the peer venv's python (``--peer-python`` overrides it)"""


def peer_python(given: str | None) -> str:
    """The peer venv's python: ``--peer-python`` if given, else ``$IMITRL_PEER_PYTHON``;
    ``SystemExit`` naming both when neither names an existing file."""
    path = given or os.environ.get(PEER_ENV)
    if not path:
        raise SystemExit(
            f"no peer python: pass --peer-python $PEER_VENV/bin/python or set {PEER_ENV} "
            "(peer_imitation.py's docstring says how to build the peer's venv)"
        )
    if not Path(path).exists():
        source = "--peer-python" if given else f"${PEER_ENV}"
        raise SystemExit(
            f"no python at {path} ({source}): build the peer's venv as peer_imitation.py's "
            f"docstring says, then pass --peer-python or set {PEER_ENV}"
        )
    return path


def imitrl_command(python: str) -> list[str]:
    """The shipped ``imitrl`` command of ``python``'s venv: its console script (beside
    ``python``, as pip installs it), else ``python -m imitrl`` (the same ``main``)."""
    script = Path(python).parent / "imitrl"
    return [str(script)] if script.exists() else [python, "-m", "imitrl"]


def byte_compile_imitrl() -> str:
    """Byte-compile imitrl's modules (as ``pip install`` does for an installed package)
    before anything is timed; returns a line saying so, for the results file.

    The peer's venv was installed with pip, which compiles every module once; imitrl
    runs from its editable checkout, and a machine that sets ``PYTHONDONTWRITEBYTECODE``
    (these do) never caches its bytecode, so each imitrl child would compile its ~100
    modules from source at every start (0.05-0.1 s measured here) and the peer's would
    not. ``compileall`` writes the caches whatever that variable says."""
    import compileall

    import imitrl

    root = Path(imitrl.__file__).resolve().parent
    if not compileall.compile_dir(str(root), quiet=1):
        raise RuntimeError(f"byte-compiling {root} failed")
    return f"imitrl's modules byte-compiled before the timed runs ({_report.portable(root)})"


SRC = HERE.parents[1] / "src"
"""this checkout's imitrl: first on every imitrl child's path, whichever venv runs it"""

OPTIONAL = ("ray", "mujoco", "metaworld", "pyarrow", "av", "h5py", "huggingface-hub", "minari")
"""imitrl's optional dependencies (its extras) worth naming in a report: TorchRL imports
ray and mujoco at its own import when they are installed"""


def _child_env(library: str) -> dict[str, str]:
    """The environment of a child: the peer's child sees no PYTHONPATH of ours; an imitrl
    child imports this checkout's ``src`` first."""
    env = dict(os.environ)
    if library == "imitation":
        env.pop("PYTHONPATH", None)
    else:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(SRC), env.get("PYTHONPATH")) if p)
    return env


def imitrl_install(python: str, *, timeout: float = 120) -> dict:
    """What runs imitrl's children: ``python``, the imitrl it imports (this checkout's, or
    ``RuntimeError``), the versions of its stack and which of :data:`OPTIONAL` its venv
    holds.

    Each library runs from its own install: the peer from a venv with imitation and what
    it requires; imitrl from ``python``'s venv. The recommended one for a timed run holds
    imitrl's requirements alone (no extras; the module docstrings of ``peer_imitation.py``
    and ``peer_gail.py`` say how to build it): TorchRL imports ray and mujoco whenever
    they are installed, 0.3-0.35 s more of imports in a venv with every extra (measured
    on ``imitrl gail``'s imports, 6 alternating runs each, load 0.8-1.0)."""
    if shutil.which(python) is None:
        raise RuntimeError(
            f"no python at {python}: build imitrl's venv as peer_imitation.py's docstring "
            "says, or pass --imitrl-python"
        )
    code = (
        "import json, importlib.metadata as m, imitrl\n"
        "names = ('torch', 'torchrl', 'tensordict', 'gymnasium', 'numpy')\n"
        "have = {d.metadata['Name'].lower(): d.version for d in m.distributions()}\n"
        "print(json.dumps({'imitrl': imitrl.__file__, 'have': have,"
        " 'versions': {n: have.get(n) for n in names}}))"
    )
    proc = subprocess.run(
        [python, "-c", code], capture_output=True, text=True, timeout=timeout,
        env=_child_env("imitrl"),
    )  # fmt: skip
    if proc.returncode != 0:
        raise RuntimeError(f"{python} cannot import imitrl: {proc.stderr[-2000:]}")
    info = json.loads(proc.stdout)
    if not Path(info["imitrl"]).resolve().is_relative_to(SRC.resolve()):
        raise RuntimeError(f"{python} imports imitrl from {info['imitrl']}, not from {SRC}")
    return {
        "python": _report.portable(python),
        "imitrl": _report.portable(info["imitrl"]),
        "versions": info["versions"],
        "optional_packages": [n for n in OPTIONAL if n in info["have"]],
    }


def _call(
    cmd: list[str], library: str, timeout: float, result: Path | None = None
) -> tuple[float, dict]:
    """Run ``cmd``; ``(wall s, the JSON it wrote to result)`` (``result`` None: ``cmd``'s
    last argument)."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=timeout, env=_child_env(library)
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(
            f"{library} child failed ({proc.returncode}): {' '.join(cmd[:3])} ...\n"
            f"{proc.stderr[-3000:]}"
        )
    return wall, json.loads(Path(cmd[-1] if result is None else result).read_text())


def run_once(
    task: Task,
    seed: int,
    library: str,
    *,
    peer_python: str | None,
    workdir: Path,
    timeout: float,
    protocol: str = "own",
    imitrl_loss: str = "default",
    imitrl_python: str = sys.executable,
    process: str = "plain",
) -> dict:
    """One (task, protocol, library, process, seed) run as a fresh process: its wall
    time and report (``process``: how imitrl's child runs, ``tasks.PROCESSES``)."""
    result = workdir / f"{task.name}-{protocol}-{library}-{process}-{seed}.json"
    spec = json.dumps(task.spec(seed, protocol, imitrl_loss, process))
    if library == "imitrl":
        cmd = [imitrl_python, str(IMITRL_RUN), spec, str(result)]
    elif peer_python is None:
        raise ValueError("imitation's run needs the peer venv's python")
    else:
        cmd = [peer_python, str(PEER_RUN), "run", spec, str(result)]
    wall, out = _call(cmd, library, timeout)
    return {
        "task": task.name, "protocol": protocol, "library": library, "seed": seed,
        "wall": wall, **out, "process": process,
    }  # fmt: skip


def plan(quick: bool) -> tuple[tuple[str, str, str], ...]:
    """:data:`PLAN`, or its imitrl runs alone (``--quick``: no peer venv)."""
    return tuple(job for job in PLAN if job[0] == "imitrl") if quick else PLAN


def order(tasks: list, seeds: int, jobs: tuple, *, quick: bool = False) -> list[tuple]:
    """The runs ``(task, seed, *job)``: every task with every job at every seed, in turn;
    ``quick`` (the smoke run): every task and every job at least once, paired in turn
    (task ``i`` with job ``i``, each list cycling), ``max(tasks, jobs)`` runs per seed."""
    if not quick:
        return [(t, s, *job) for t in tasks for s in range(seeds) for job in jobs]
    n = max(len(tasks), len(jobs))
    return [
        (tasks[i % len(tasks)], s, *jobs[i % len(jobs)]) for i in range(n) for s in range(seeds)
    ]


def run_all(
    tasks: list[Task],
    seeds: int,
    jobs: tuple[tuple[str, str, str], ...] = PLAN,
    *,
    peer_python: str | None,
    timeout: float,
    concurrent: bool = False,
    imitrl_loss: str = "default",
    imitrl_python: str = sys.executable,
    log=print,
) -> list[dict]:
    """Every (task, seed), and for each the (library, protocol, process) ``jobs`` in
    turn (:data:`PLAN`), one process at a time; ``concurrent`` (the smoke run, timings
    moot): :func:`order`'s quick pairs, :data:`QUICK_WORKERS` at once."""
    runs = order(tasks, seeds, jobs, quick=concurrent)
    with tempfile.TemporaryDirectory(prefix="peer-imitation-") as tmp:

        def one(job: tuple[Task, int, str, str, str]) -> dict:
            task, seed, library, protocol, process = job
            r = run_once(
                task, seed, library, peer_python=peer_python, workdir=Path(tmp),
                timeout=timeout, protocol=protocol, imitrl_loss=imitrl_loss,
                imitrl_python=imitrl_python, process=process,
            )  # fmt: skip
            phases = ", ".join(f"{k} {v:.2f}" for k, v in r["phases"].items())
            log(
                f"{task.name} {protocol} seed {seed} {library:9s} {process:15s} wall "
                f"{r['wall']:.2f} s ({phases}); returns {r['returns']}"
            )
            return r

        if concurrent:
            with ThreadPoolExecutor(min(len(runs), QUICK_WORKERS)) as pool:
                return list(pool.map(one, runs))
        return [one(job) for job in runs]


# --------------------------------------------------------------- the expert check
def check_batches(n: int = 2000, seed: int = 0) -> dict[str, torch.Tensor]:
    """Observations to label: every FrozenLake state; CartPole states spread over the
    region its episodes visit; Pendulum angles and velocities over the whole circle,
    with velocities at and around 0 (the swing-up's special case) and angles across
    the LQR switch (``cos th = 0.9``)."""
    g = torch.Generator().manual_seed(seed)
    scale = torch.tensor([2.4, 3.0, 0.21, 3.0])
    cartpole = (2 * torch.rand(n, 4, generator=g) - 1) * scale
    th = (2 * torch.rand(n, generator=g) - 1) * math.pi
    w = (2 * torch.rand(n, generator=g) - 1) * 8.0
    w[: n // 10] = 0.0
    w[n // 10 : n // 5] *= 1e-3
    th[n // 5 : n // 4] = math.acos(0.9) * (1 + 1e-3 * (2 * torch.rand(n // 20, generator=g) - 1))
    pendulum = torch.stack([th.cos(), th.sin(), w], dim=-1).to(torch.float32)
    return {"FrozenLake-v1": torch.arange(16), "CartPole-v1": cartpole, "Pendulum-v1": pendulum}


def check_experts(peer_python: str, *, timeout: float) -> dict:
    """imitrl's experts and the peer script's copies on the same batches: discrete labels
    equal, continuous within 1e-5; raises ``RuntimeError`` naming the first disagreement."""
    batches = check_batches()
    with tempfile.TemporaryDirectory(prefix="peer-imitation-check-") as tmp:
        obs_file = Path(tmp) / "obs.json"
        obs_file.write_text(json.dumps({k: v.tolist() for k, v in batches.items()}))
        cmd = [peer_python, str(PEER_RUN), "check", str(obs_file), str(Path(tmp) / "out.json")]
        _, peer = _call(cmd, "imitation", timeout)
    report = {}
    for env_id, obs in batches.items():
        td = TensorDict({keys.OBSERVATION: obs}, batch_size=[obs.shape[0]])
        ours = EXPERTS[env_id]()(td).get(keys.EXPERT_ACTION)
        theirs = torch.tensor(peer[env_id], dtype=ours.dtype).reshape(ours.shape)
        if ours.dtype.is_floating_point:
            diff = float((ours - theirs).abs().max())
            agree = diff <= 1e-5
        else:
            diff = int((ours != theirs).sum())
            agree = diff == 0
        if not agree:
            raise RuntimeError(
                f"the peer's {env_id} expert disagrees with imitrl's on the check batch "
                f"(max difference / mismatches: {diff}): fix _peer_imitation/peer_run.py"
            )
        report[env_id] = {"observations": int(obs.shape[0]), "max_difference": diff}
    return report


def peer_versions(peer_python: str, *, timeout: float = 120) -> dict[str, str]:
    """``pip list`` of the peer's venv, ``{name: version}``."""
    proc = subprocess.run(
        [peer_python, "-m", "pip", "list", "--format=json"],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=_child_env("imitation"),
    )
    if proc.returncode != 0:
        raise RuntimeError(f"pip list in the peer's venv failed: {proc.stderr[-2000:]}")
    return {p["name"]: p["version"] for p in json.loads(proc.stdout)}


# ------------------------------------------------------------------ references
def frozenlake_exact(table: list[int]) -> float:
    """Exact success probability of a greedy FrozenLake table within the 100-step limit."""
    from imitrl.tabular import TabularMDP, success_probability

    mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95)
    return success_probability(mdp, torch.tensor(table))


def expert_returns(task: Task, seeds: int) -> list[float]:
    """The expert's score per seed: FrozenLake its exact success (the same for every
    seed); elsewhere its greedy mean return on imitrl's evaluation episodes of that
    seed (imitrl's lanes; imitation's 50 vector envs reset from other states)."""
    from imitrl.envs import make_env
    from imitrl.evaluation import evaluate

    expert = EXPERTS[task.env_id]()
    if task.env_id == "FrozenLake-v1":
        table = expert(TensorDict({keys.OBSERVATION: torch.arange(16)}, [16]))
        return [frozenlake_exact(table.get(keys.EXPERT_ACTION).tolist())] * seeds
    out = []
    for seed in range(seeds):
        spec = task.spec(seed)
        lanes = min(spec["eval_lanes"]["imitrl"], task.eval_episodes)  # imitrl's states
        env = make_env(task.env_id, seed=spec["eval_seed"], num_envs=lanes)
        out.append(evaluate(env, expert, task.eval_episodes, seed=spec["eval_seed"]).mean_return)
    return out

"""imitrl's side of ``peer_imitation.py``: one (task, seed) run, as a whole process.

    python benchmarks/_peer_imitation/imitrl_run.py SPEC_JSON RESULT_JSON

``SPEC_JSON`` is :meth:`tasks.Task.spec` (a JSON string); the phase times and returns
are written to ``RESULT_JSON``. The run is what a user writes with imitrl's public API
and defaults (the learner ``imitrl bc --loss`` builds: ``--loss for_env``, an MLP on
one-hot states for FrozenLake as imitation's policy is, for the benchmark's
``default``, or the ``imitrl_loss`` registry entry; Adam at 1e-3, as imitation's BC;
``dagger`` with a fresh learner per round and
beta = 0, ``evaluate`` greedy on vector envs); under the ``matched`` protocol one learner
is trained on across rounds (``warm_start=True``), as imitation does. The task's budgets:

1. setup: the train and evaluation envs (``make_env``), the expert (FrozenLake: value
   iteration, gamma 0.95, 1000 sweeps; CartPole, Pendulum: ``imitrl.experts``), the
   demonstrations (``rollout_episodes``, cut to ``demo_steps``) in a buffer;
2. bc: the first fit, ``bc_steps`` steps on the demonstrations (``dagger``'s round 0);
3. dagger: ``rounds`` relabel rounds of ``episodes_per_round`` episodes, each followed
   by a ``round_steps`` fit of a fresh learner on the whole buffer (collection + fits);
4. evaluation: the BC learner and the final learner, ``eval_episodes`` each, on
   ``eval_lanes["imitrl"]`` lanes seeded from ``eval_seed``.

The process is a plain Python script by default (the spec's ``process`` is ``plain``:
what a user's script does, the garbage collector as Python starts it). With ``process``
``collector_trick`` it does what the ``imitrl`` command does in the process it owns
(:func:`imitrl.cli.main`, :mod:`imitrl.system.heap`): the imports with the collector
paused, then the import-time heap frozen out of its walks, then the collector on again;
``peer_imitation.py`` runs that as a row of its own. The result names the process kind
and ``gc.get_freeze_count()`` once imported (0 in a plain script).

Phases are wall-clock seconds inside this process (``imports`` from the first line of
this file); the parent measures the whole process.
"""

import time

T_START = time.perf_counter()

import gc  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

PROCESS = json.loads(sys.argv[1]).get("process", "plain") if __name__ == "__main__" else "plain"
"""the spec's process kind (``plain`` when imported, as ``runs`` imports ``EXPERTS``)"""
if PROCESS not in ("plain", "collector_trick"):
    raise SystemExit(f"unknown process {PROCESS!r}: plain or collector_trick")
if PROCESS == "collector_trick":  # the imitrl command imports this first (no torch) ...
    from imitrl.system.heap import freeze_imported

    gc.disable()  # ... then imports its modules with the collector paused

import torch  # noqa: E402

torch.set_num_threads(1)

from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc  # noqa: E402
from imitrl.data import DemonstrationBuffer  # noqa: E402
from imitrl.envs import make_env  # noqa: E402
from imitrl.evaluation import evaluate  # noqa: E402
from imitrl.experts import cartpole_expert, pendulum_expert  # noqa: E402
from imitrl.learners import FOR_ENV, TaskSpec, build, registry, resolve  # noqa: E402
from imitrl.policies import Expert  # noqa: E402
from imitrl.runtime import rollout_episodes  # noqa: E402
from imitrl.tabular import TabularMDP, greedy, value_iteration  # noqa: E402

if PROCESS == "collector_trick":
    freeze_imported()  # as the imitrl command does once its modules are imported
    gc.enable()
FROZEN = gc.get_freeze_count()
T_IMPORTED = time.perf_counter()


def frozenlake_expert() -> Expert:
    """Greedy in ``Q*`` of slippery FrozenLake (gamma 0.95, 1000 sweeps of value iteration)."""
    mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95)
    return Expert.from_table(greedy(mdp.backup(value_iteration(mdp, 1000)[-1])))


EXPERTS = {
    "FrozenLake-v1": frozenlake_expert,
    "CartPole-v1": cartpole_expert,
    "Pendulum-v1": pendulum_expert,
}


def _loss(spec: dict) -> str:
    """The benchmark's ``default`` learner is ``for_env``'s MLP on every task (on vector
    observations the same network as the registry entry ``--loss default`` names; on
    FrozenLake's integer states an MLP, as imitation's, not the registry's table)."""
    loss = spec.get("imitrl_loss", "default")
    return FOR_ENV if loss == "default" else loss


def _hidden(spec: dict, env, hidden: tuple[int, ...]) -> tuple[int, ...] | None:
    """The task's layers, except for a registry entry's logits table (integer states),
    which has none and refuses them."""
    loss, task = _loss(spec), TaskSpec.from_env(env)
    table = loss != FOR_ENV and registry.get(resolve(loss, task)).tables and task.num_states
    return None if table else hidden


def _learner(spec: dict, env, hidden: tuple[int, ...], seed: int):
    """``() -> Learner``: the task's learner, as ``imitrl dagger --loss ...`` builds it."""
    settings = {"lr": 1e-3, "seed": seed}
    layers = _hidden(spec, env, hidden)
    if layers is not None:
        settings["hidden"] = layers
    return lambda: build(_loss(spec), env, **settings)


def run(spec: dict) -> dict:
    """One run; the phases in seconds, the returns, FrozenLake's greedy tables."""
    now = time.perf_counter
    seed, eval_seed, env_id = spec["seed"], spec["eval_seed"], spec["env_id"]
    hidden = tuple(spec["hidden"])

    # -- setup: envs, expert, demonstrations
    t0 = now()
    env = make_env(env_id, seed=seed)
    lanes = min(spec["eval_lanes"]["imitrl"], spec["eval_episodes"])
    eval_env = make_env(env_id, seed=eval_seed, num_envs=lanes)
    expert = EXPERTS[env_id]()
    demos = rollout_episodes(env, expert, spec["demo_episodes"])
    if spec["demo_steps"] is not None:
        demos = demos[: spec["demo_steps"]]
    buffer = DemonstrationBuffer(action_spec=env.action_spec)
    buffer.extend(demos)
    setup = now() - t0

    # -- BC (dagger's round 0) and DAgger; fits and evaluations timed inside the loop
    fit_seconds: list[float] = []
    evals: dict[str, float] = {}
    tables: dict[str, list[int]] = {}
    eval_seconds = 0.0
    last = spec["rounds"]

    def train(learner, rows):
        steps = spec["bc_steps"] if not fit_seconds else spec["round_steps"]
        t = now()
        result = fit_bc(learner, rows, BCConfig(steps, batch_size=spec["batch_size"], seed=seed))
        fit_seconds.append(now() - t)
        return result

    def on_fit(k, learner):
        nonlocal eval_seconds
        if k not in (0, last):
            return None
        t = now()
        name = "bc" if k == 0 else "final"
        evals[name] = evaluate(eval_env, learner, spec["eval_episodes"], seed=eval_seed).mean_return
        if env_id == "FrozenLake-v1":
            tables[name] = learner.greedy_table().tolist()
        eval_seconds += now() - t
        return None

    config = DAggerConfig(
        rounds=last + 1,
        episodes_per_round=spec["episodes_per_round"],
        bc=BCConfig(spec["round_steps"], batch_size=spec["batch_size"], seed=seed),
        warm_start=spec["protocol"] == "matched",
        seed=seed,
    )
    t0 = now()
    new_learner = _learner(spec, env, hidden, seed)  # () -> a fresh learner
    result = dagger(EnvSource(env), expert, new_learner, buffer, config, train=train, on_fit=on_fit)
    loop = now() - t0
    bc = fit_seconds[0]
    dagger_s = loop - bc - eval_seconds
    return {
        "library": "imitrl",
        "phases": {
            "imports": T_IMPORTED - T_START,
            "setup": setup,
            "bc": bc,
            "dagger": dagger_s,
            "dagger_fit": sum(fit_seconds[1:]),
            "dagger_collect": dagger_s - sum(fit_seconds[1:]),
            "evaluation": eval_seconds,
        },
        "returns": evals,
        "greedy_tables": tables,
        "rows": result.rounds[-1].rows_trained,
        "demo_rows": int(demos.shape[0]),
    }


def main() -> None:
    spec = json.loads(sys.argv[1])
    out = {**run(spec), "process": PROCESS, "gc_frozen": FROZEN}
    out["phases"]["in_process"] = time.perf_counter() - T_START
    Path(sys.argv[2]).write_text(json.dumps(out))


if __name__ == "__main__":
    main()

"""imitrl's GAIL and AIRL side of ``peer_gail.py``: one (task, protocol, seed) run, as a whole process.

    python benchmarks/_peer_imitation/gail_imitrl.py SPEC_JSON RESULT_JSON

``SPEC_JSON`` is :meth:`gail_tasks.GailTask.spec`. The run is what ``imitrl gail
--num-envs LANES`` (or ``imitrl airl``, for the task's ``method``) trains, through the
public API, with the spec's settings, as a user's Python script: the process is a plain
script unless the spec's ``process`` is ``collector_trick``, which does what the ``imitrl``
command does in the process it owns (:func:`imitrl.cli.main`, :mod:`imitrl.system.heap`):
the imports with the garbage collector paused, then the import-time heap frozen out of
its walks, then the collector on again. What the command does beyond this script (the
expert's and the untrained learner's evaluations, the logger, results.json, the
checkpoint, curves.png) is ``peer_gail.py``'s ``command`` row, the shipped command itself.

1. setup: the generator's env (``make_env``, ``lanes`` lanes), ``demo_episodes`` greedy
   episodes of the built-in expert (``rollout_episodes``), the learner
   (as ``imitrl gail`` builds it by default: ``cross_entropy``'s categorical MLP for
   discrete actions,
   ``gaussian_nll``, a tanh-normal with a learned state-independent log-std, for
   continuous ones; hidden layers ``learner_hidden``, 64, 64);
2. train: :func:`imitrl.algorithms.adversarial.gail` (or ``airl``) for ``total_steps``;
3. evaluation: the learner greedy (``evaluate``) on ``eval_lanes`` lanes seeded
   ``eval_seed``, ``eval_episodes`` episodes.
"""

import time

T_START = time.perf_counter()

import gc  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

PROCESS = json.loads(sys.argv[1]).get("process", "plain") if __name__ == "__main__" else "plain"
"""the spec's process kind: ``plain`` or ``collector_trick``"""
if PROCESS not in ("plain", "collector_trick"):
    raise SystemExit(f"unknown process {PROCESS!r}: plain or collector_trick")
if PROCESS == "collector_trick":  # the imitrl command imports this first (no torch) ...
    from imitrl.system.heap import freeze_imported

    gc.disable()  # ... then imports its modules with the collector paused

import torch  # noqa: E402

torch.set_num_threads(1)

from torchrl.envs.utils import ExplorationType  # noqa: E402

from imitrl.algorithms.adversarial import AIRLConfig, GAILConfig, airl, gail  # noqa: E402
from imitrl.data import DemonstrationBuffer  # noqa: E402
from imitrl.envs import make_env  # noqa: E402
from imitrl.evaluation import evaluate  # noqa: E402
from imitrl.experts import cartpole_expert, pendulum_expert  # noqa: E402
from imitrl.learners import build  # noqa: E402
from imitrl.runtime import rollout_episodes  # noqa: E402

if PROCESS == "collector_trick":
    freeze_imported()  # as the imitrl command does once its modules are imported
    gc.enable()
FROZEN = gc.get_freeze_count()
T_IMPORTED = time.perf_counter()
EXPERTS = {"CartPole-v1": cartpole_expert, "Pendulum-v1": pendulum_expert}


def algorithm_config(spec: dict) -> GAILConfig | AIRLConfig:
    """The training config the spec's settings give (``imitrl gail``'s, or ``imitrl
    airl``'s, ``algorithm_config()`` with :func:`gail_tasks.command_flags`: a test holds
    the two equal)."""
    s, seed = spec["settings"], spec["seed"]
    fields = dict(
        total_steps=spec["total_steps"], rollout_steps=spec["rollout_steps"],
        ppo_epochs=s["ppo_epochs"], minibatch_size=s["minibatch_size"],
        discriminator_updates=s["discriminator_updates"],
        discriminator_batch=s["discriminator_batch"], discriminator_lr=s["discriminator_lr"],
        discriminator_hidden=tuple(s["discriminator_hidden"]), gamma=s["gamma"], seed=seed,
    )  # fmt: skip
    if spec["method"] == "airl":
        return AIRLConfig(
            **fields, clip_epsilon=s["clip_epsilon"], entropy_weight=s["entropy_weight"]
        )
    return GAILConfig(**fields)


def run(spec: dict) -> dict:
    now = time.perf_counter
    seed, env_id, s = spec["seed"], spec["env_id"], spec["settings"]
    t0 = now()
    env = make_env(env_id, seed=seed, num_envs=spec["lanes"])
    demo_env = make_env(env_id, seed=seed)
    buffer = DemonstrationBuffer(action_spec=demo_env.action_spec_unbatched)
    buffer.extend(rollout_episodes(demo_env, EXPERTS[env_id](), spec["demo_episodes"]))
    # imitrl gail's default learner: a head with log pi, and a value head for PPO
    hidden = tuple(spec["learner_hidden"])
    learner = build("default", demo_env, hidden=hidden, lr=s["lr"], seed=seed, value=True)
    config = algorithm_config(spec)
    setup = now() - t0

    t0 = now()
    if spec["method"] == "airl":
        result, _ = airl(env, learner, buffer, config)
    else:
        result = gail(env, learner, buffer, config)
    train = now() - t0

    t0 = now()
    eval_env = make_env(env_id, seed=spec["eval_seed"], num_envs=spec["eval_lanes"])
    ev = evaluate(
        eval_env, learner.policy, spec["eval_episodes"], seed=spec["eval_seed"],
        exploration=ExplorationType.DETERMINISTIC,
    )  # fmt: skip
    evaluation = now() - t0
    return {
        "library": "imitrl",
        "phases": {
            "imports": T_IMPORTED - T_START,
            "setup": setup,
            "train": train,
            "evaluation": evaluation,
        },
        "returns": {"final": float(ev.mean_return)},
        "env_steps": int(result.env_steps),
        "demo_rows": len(buffer),
        "process": PROCESS,
        "gc_frozen": FROZEN,
    }


def main() -> None:
    out = run(json.loads(sys.argv[1]))
    out["phases"]["in_process"] = time.perf_counter() - T_START
    Path(sys.argv[2]).write_text(json.dumps(out))


if __name__ == "__main__":
    main()

"""Meta-World from a camera on CPU: render cost, and DAgger with a privileged state expert.

1. Render cost. Frames of LeRobot's ``corner2`` camera (``obs_type="pixels_agent_pos"``)
   rendered headless by MuJoCo (``MUJOCO_GL=egl``, Mesa's llvmpipe on these machines) at
   84x84 and 480x480, with shadows and reflections on (MuJoCo's default, and the env's:
   LeRobot's frames) and off (``fast_render=True``, what part 2 uses): seconds per env
   step, frame included, against the state-only step.
2. BC vs DAgger from pixels. One MT1 task (``reach-v3``) seen through an 84x84 camera
   plus the hand's 4-d ``agent_pos``; the expert is the task's scripted policy reading
   the 39-d state the learner does not see (privileged). Per seed: ``demos`` expert
   episodes, then ``dagger`` (round 0 = BC; relabel rounds of the learner's own episodes,
   beta 0), a fresh Nature-CNN learner (``build("for_env", env, state=True)``, state beside the image)
   each round; BC and the last DAgger learner are evaluated on the same held-out
   episodes; success as in ``metaworld_mt10.py``.

    python benchmarks/metaworld_pixels.py            # full run, refreshes the README block
    python benchmarks/metaworld_pixels.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _report
from _common import source
from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, dagger
from imitrl.algorithms.beta_schedules import Constant, Exponential
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.evaluation import evaluate, wilson_interval
from imitrl.experts import metaworld_expert
from imitrl.learners import build
from imitrl.runtime import rollout_episodes

NAME = "metaworld_pixels"
TASK = "reach-v3"
SETTINGS = ((None, True), (84, True), (84, False), (480, True), (480, False))
"""(camera size, fast_render) of the render-cost table (None: the state alone)"""
FULL = {"seeds": 3, "demos": 5, "rounds": 4, "episodes": 3, "steps": 600, "eval": 10,
        "max_steps": 150, "settings": SETTINGS}  # fmt: skip
QUICK = {"seeds": 1, "demos": 1, "rounds": 2, "episodes": 1, "steps": 5, "eval": 2,
         "max_steps": 20, "settings": SETTINGS[:2]}  # fmt: skip


def _env(size: int | None, seed: int, lanes: int, budget: dict, fast: bool = True,
         task: str = TASK):  # fmt: skip
    kwargs = {} if size is None else {"obs_type": "pixels_agent_pos", "width": size,
                                      "height": size, "fast_render": fast}  # fmt: skip
    return make_env(
        f"metaworld/{task}",
        seed=seed,
        num_envs=lanes,
        max_episode_steps=budget["max_steps"],
        env_kwargs=kwargs,
    )


def render_cost(budget: dict) -> list[dict]:
    """Seconds per env step (frame included) for each camera setting."""
    out = []
    for size, fast in budget["settings"]:
        env = _env(size, 0, 1, budget, fast)
        expert = metaworld_expert(TASK, observation_key=keys.ENVIRONMENT_STATE if size else None)
        rollout_episodes(env, expert, 1, seed=0)  # warm: the renderer's first context
        t = time.perf_counter()
        rows = rollout_episodes(env, expert, 1, seed=1)
        seconds = (time.perf_counter() - t) / rows.shape[0]
        env.close()
        out.append({"size": size, "fast_render": fast, "seconds_per_step": seconds})
        print(f"render {size} fast={fast}: {seconds * 1e3:.1f} ms/step", file=sys.stderr)
    return out


def beta_schedule(budget: dict) -> Exponential | Constant:
    """DAgger's beta: Ross et al.'s schedule where ``budget`` names ``beta_decay``, else 0
    in every round (the section's DAgger, this script's own budgets)."""
    return Exponential(budget["beta_decay"]) if budget.get("beta_decay") else Constant(0.0)


def dagger_cell(seed: int, budget: dict, task: str = TASK) -> dict:
    """BC and DAgger from an 84x84 camera with the privileged expert, one task and seed
    (``metaworld_pixels_mt10.py`` runs it on every MT10 task)."""
    torch.manual_seed(seed)
    env = _env(84, seed, budget["episodes"], budget, task=task)
    expert = metaworld_expert(task, observation_key=keys.ENVIRONMENT_STATE)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, expert, budget["demos"], seed=seed))
    scores: dict[int, dict] = {}
    eval_env = _env(84, 10_000 + seed, min(budget["eval"], 5), budget, task=task)

    def on_fit(k: int, learner) -> None:
        if k in (0, budget["rounds"] - 1):
            ev = evaluate(eval_env, learner, budget["eval"], seed=10_000 + seed)
            scores[k] = {"success": ev.success_rate, "episodes": budget["eval"]}

    out = dagger(
        source(env, exploration=None, max_steps=budget["max_steps"]),
        expert,
        lambda: build("for_env", env, state=True, seed=seed, lr=1e-3),
        buffer,
        DAggerConfig(
            rounds=budget["rounds"],
            episodes_per_round=budget["episodes"],
            bc=BCConfig(num_steps=budget["steps"], batch_size=128, seed=seed),
            seed=seed,
            beta=beta_schedule(budget),
        ),
        on_fit=on_fit,
    )
    ref = evaluate(eval_env, expert, budget["eval"], seed=10_000 + seed)
    env.close()
    eval_env.close()
    return {
        "task": task,
        "seed": seed,
        "bc": scores[0],
        "dagger": scores[budget["rounds"] - 1],
        "expert": {"success": ref.success_rate, "episodes": budget["eval"]},
        "rows": out.rounds[-1].rows_trained,
        "betas": [r.beta_next for r in out.rounds[:-1]],  # each relabel round's, in order
    }


def pooled(cells: list[dict], who: str) -> tuple[int, int]:
    """(successes, episodes) of ``who`` (expert, bc, dagger) over ``cells``: each cell's
    success rate is over exactly its ``episodes`` held-out episodes."""
    k = sum(round(c[who]["success"] * c[who]["episodes"]) for c in cells)
    return k, sum(c[who]["episodes"] for c in cells)


def fmt_pooled(k: int, n: int) -> str:
    """``k / n [95% Wilson] (k/n)``."""
    lo, hi = wilson_interval(k, n)
    return f"{k / n:.2f} [{lo:.2f}, {hi:.2f}] ({k}/{n})"


def markdown(payload: dict) -> str:
    b, cells = payload["budget"], payload["cells"]
    state = next(r for r in payload["render"] if r["size"] is None)["seconds_per_step"]
    render = _report.table(
        ["camera", "shadows and reflections", "ms per step (frame included)", "x state step"],
        [
            [f"{r['size']}x{r['size']}" if r["size"] else "none (state)",
             "-" if r["size"] is None else ("off" if r["fast_render"] else "on"),
             f"{r['seconds_per_step'] * 1e3:.1f}", f"{r['seconds_per_step'] / state:.1f}"]
            for r in payload["render"]
        ],
    )  # fmt: skip
    results = _report.table(
        ["policy", "success (pooled over seeds, 95% Wilson)"],
        [[who, fmt_pooled(*pooled(cells, who))] for who in ("expert", "bc", "dagger")],
    )
    return "\n\n".join(
        [
            f"`{TASK}`, LeRobot's corner2 camera, headless MuJoCo (MUJOCO_GL="
            f"{os.environ.get('MUJOCO_GL', 'egl')}), 1 torch thread; 1-min load "
            f"{payload['load_average_start'][0]:.2f} at the start; wall time "
            f"{payload['wall_seconds'] / 60:.1f} min.",
            render,
            f"BC vs DAgger from an 84x84 camera plus the hand's agent_pos, the expert reading "
            f"the 39-d state: {b['seeds']} seeds, {b['demos']} demonstrations, "
            f"{b['rounds'] - 1} relabel rounds x {b['episodes']} episodes, fresh Nature-CNN "
            f"learner each round ({b['steps']} steps x batch 128), {b['eval']} held-out "
            f"episodes of at most {b['max_steps']} steps; DAgger's last fit saw "
            f"{[c['rows'] for c in cells]} rows.",
            results,
        ]
    )


def main(argv: list[str] | None = None) -> None:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    torch.set_num_threads(1)
    os.environ.setdefault("MUJOCO_GL", "egl")
    budget = QUICK if args.quick else FULL
    load, t0 = os.getloadavg(), time.perf_counter()
    render = render_cost(budget)
    cells = []
    for seed in range(budget["seeds"]):
        cells.append(dagger_cell(seed, budget))
        print(f"seed {seed}: {cells[-1]}", file=sys.stderr, flush=True)
    payload = {
        "budget": budget,
        "render": render,
        "cells": cells,
        "wall_seconds": time.perf_counter() - t0,
        "load_average_start": list(load),
    }
    text = markdown(payload)
    path = _report.write(NAME, payload, text, out_dir=out_dir)
    print(text)
    print(f"results: {path}")


if __name__ == "__main__":
    main()

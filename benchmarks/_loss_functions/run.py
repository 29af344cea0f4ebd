"""The cells of ``loss_functions.py``: every (task, loss, seed) trained, every task's references.

Every random draw of a cell flows from its seed (the learner's initialisation, its
minibatches, its sampling, the envs), so a cell gives the same digits whenever and
wherever (``--jobs``) it runs.
"""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, replace
from typing import Any

import torch

from _common import DET, rollout, source
from _loss_functions.tasks import tasks as task_table
from imitrl.algorithms import DAggerConfig, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.data.chunks import add_chunk_labels
from imitrl.objectives import registry
from imitrl.objectives.registry import Learner
from imitrl.policies import as_actor


def reference_cell(task_name: str, seed: int, quick_mode: bool) -> list[dict]:
    """The expert's and a uniformly random policy's scores on the task's protocol."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    task = task_table(quick_mode)[task_name]()
    return [
        {"task": task_name, "policy": who, "seed": seed, **result}
        for who, result in (
            ("expert", task.expert_score(seed)),
            ("random", task.random_score(seed)),
        )
    ]


def loss_cell(task_name: str, loss: str, seed: int, quick_mode: bool) -> list[dict]:
    """Train ``loss`` on ``task_name`` with ``seed``: one row for BC, one for DAgger."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)  # global draws (TorchRL's samplers) start from the seed too
    t0 = time.perf_counter()
    task = task_table(quick_mode)[task_name]()
    proto = task.protocol
    spec = task.spec()
    config = replace(proto.learner, seed=seed)
    bc = replace(proto.bc, seed=seed)

    # 1. demonstrations: the expert drives the env, every row is labelled
    env = task.env(seed=seed, lanes=proto.episodes_per_round)
    expert = task.expert()
    buffer = DemonstrationBuffer(num_states=spec.num_states)
    buffer.extend(
        rollout(
            env, as_actor(expert), proto.demo_episodes, exploration=DET, max_steps=task.max_steps()
        )
    )
    demo_rows = len(buffer)

    # 2. DAgger, whose round 0 is BC; evaluate the first and the last fit
    results: dict[int, dict] = {}
    fit_seconds: list[float] = []

    horizon = registry.get(loss).horizon

    def timed_fit(learner: Learner, buf: DemonstrationBuffer):
        t = time.perf_counter()
        # a chunked learner: every row's label chunk, from the (relabelled) rows of its
        # episode (imitrl.data.chunks); otherwise what dagger does without train=, timed
        rows = buf if horizon is None else add_chunk_labels(buf.data, horizon)
        out = fit_bc(learner, rows, bc)
        fit_seconds.append(time.perf_counter() - t)
        return out

    def on_fit(k: int, learner: Learner) -> None:
        if k in (0, proto.rounds - 1):
            t = time.perf_counter()
            result = task.score(learner.policy, learner.exploration, seed)
            result.update(task.extras(learner, seed))
            result["eval_seconds"] = time.perf_counter() - t
            results[k] = result

    out = dagger(
        source(env, exploration=None, max_steps=task.max_steps()),  # as each learner acts
        expert,
        lambda: registry.build(loss, spec, config),
        buffer,
        DAggerConfig(
            rounds=proto.rounds, episodes_per_round=proto.episodes_per_round, bc=bc, seed=seed
        ),
        on_fit=on_fit,
        train=timed_fit,
    )
    env.close()
    exploration = str(out.learner.exploration).split(".")[-1].lower()
    rows = []
    for algorithm, k in (("bc", 0), ("dagger", proto.rounds - 1)):
        record = out.rounds[k]
        rows.append(
            {
                "task": task_name,
                "loss": loss,
                "seed": seed,
                "algorithm": algorithm,
                "exploration": exploration,
                "rows_trained": record.rows_trained,
                "demo_rows": demo_rows,
                "final_loss": record.bc.final_loss,
                "fit_seconds": fit_seconds[k],
                **results[k],
            }
        )
    rows[-1]["cell_seconds"] = rows[0]["cell_seconds"] = time.perf_counter() - t0
    return rows


def run(
    *,
    tasks: list[str],
    losses: list[str] | None,
    seeds: int,
    quick_mode: bool,
    jobs: int = 1,
) -> dict[str, Any]:
    """Every (loss, task, seed) cell and the expert/random references; returns the raw rows."""
    factories = task_table(quick_mode)
    cells, refs = [], []
    for task_name in tasks:
        spec = factories[task_name]().spec()
        for seed in range(seeds):
            refs.append((task_name, seed, quick_mode))
            for loss in registry.names(spec):
                if losses is None or loss in losses:
                    cells.append((task_name, loss, seed, quick_mode))
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            ref_rows = [r for rows in pool.map(reference_cell, *zip(*refs)) for r in rows]
            rows = [r for rs in pool.map(loss_cell, *zip(*cells)) for r in rs]
    else:
        ref_rows = [r for args in refs for r in reference_cell(*args)]
        rows = []
        for i, args in enumerate(cells):
            t = time.perf_counter()
            rows += loss_cell(*args)
            print(
                f"[{i + 1}/{len(cells)}] {args[0]} {args[1]} seed {args[2]}: "
                f"bc {rows[-2]['score']:.3f} dagger {rows[-1]['score']:.3f} "
                f"({time.perf_counter() - t:.1f} s)",
                flush=True,
            )
    protocols = {t: asdict(factories[t]().protocol) for t in tasks}
    return {"rows": rows, "references": ref_rows, "protocols": protocols}

"""The cells of ``loss_functions.py``: every (task, loss, seed) trained, every task's references.

Every random draw of a cell flows from its seed (the learner's initialisation, its
minibatches, its sampling, the envs), so a cell gives the same digits whenever and
wherever (``--jobs``) it runs.
"""

from __future__ import annotations

import importlib
import multiprocessing
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from typing import Any

import torch
from tensordict import TensorDictBase

from _common import DET, rollout, source
from _loss_functions.tasks import TaskDef, build
from imitrl import keys
from imitrl.algorithms import DAggerConfig, dagger, fit_bc
from imitrl.algorithms.beta_schedules import Constant, Exponential
from imitrl.data import DemonstrationBuffer
from imitrl.learners import FOR_ENV, Learner, registry
from imitrl.policies import as_actor

WORKER_CELLS = 20
"""cells a worker process runs before it is replaced (its memory handed back)"""


def reference_cell(defn: TaskDef, seed: int, quick_mode: bool) -> list[dict]:
    """The expert's and a uniformly random policy's scores on the task's protocol."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    task = build(defn, quick_mode)
    return [
        {"task": defn.name, "policy": who, "seed": seed, **result}
        for who, result in (
            ("expert", task.expert_score(seed)),
            ("random", task.random_score(seed)),
        )
    ]


def loss_cell(
    defn: TaskDef,
    loss: str,
    seed: int,
    quick_mode: bool,
    probe: Callable[[TensorDictBase], dict] | None = None,
) -> list[dict]:
    """Train ``loss`` on the task ``defn`` with ``seed``: one row for BC, one for DAgger
    (BC alone for a task without an expert). ``probe``: called on DAgger's rows (the
    demonstrations and every relabel round's) after its last round; what it returns is
    the DAgger row's ``probe`` (``dagger_labels.py``'s measurement)."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)  # global draws (TorchRL's samplers) start from the seed too
    t0, cpu0 = time.perf_counter(), time.process_time()
    task = build(defn, quick_mode)
    proto = task.protocol
    spec = task.spec()
    config = replace(proto.learner, seed=seed)
    # the loss's own recipe: ACT's minibatch, Diffusion Policy's warm-up and cosine decay
    cell = _Cell(task, loss, registry.fit_config(loss, replace(proto.bc, seed=seed)), seed)

    # 1. demonstrations: a recorded dataset, or the expert drives the env (every row labelled)
    env = task.env(seed=seed, lanes=proto.episodes_per_round)
    expert = task.expert()
    buffer = DemonstrationBuffer(num_states=spec.num_states)
    recorded = task.demonstrations(env)
    if recorded is None:
        recorded = rollout(
            env, as_actor(expert), proto.demo_episodes, exploration=DET, max_steps=task.max_steps()
        )
    buffer.extend(recorded)
    demo_rows = len(buffer)

    # 2. DAgger, whose round 0 is BC; evaluate the first and the last fit
    if expert is None:  # a dataset alone: BC only
        learner = config.build(loss, spec)
        fit = cell.fit(learner, buffer)
        cell.score(0, learner)
        records = [(learner, len(buffer), fit)]
    else:
        out = dagger(
            source(env, exploration=None, max_steps=task.max_steps()),  # as each learner acts
            expert,
            lambda: config.build(loss, spec),
            buffer,
            DAggerConfig(
                rounds=proto.rounds,
                episodes_per_round=proto.episodes_per_round,
                warm_start=cell.warm,
                beta=Constant(0.0) if proto.beta_decay is None else Exponential(proto.beta_decay),
                bc=cell.bc,
                seed=seed,
            ),
            on_fit=cell.score,
            train=cell.fit,
        )
        learner = out.learner
        records = [(learner, r.rows_trained, r.bc) for r in out.rounds]
        if probe is not None:
            cell.results[proto.rounds - 1]["probe"] = probe(buffer.data[: len(buffer)])
    # 3. BC at DAgger's query budget: as many expert-labelled rows, from the expert's states
    if proto.matched and expert is not None and proto.rounds > 1:
        records.append(cell.matched(env, expert, records[-1][1], config.build(loss, spec)))
    env.close()
    rows = cell.rows(records, demo_rows, str(learner.exploration).split(".")[-1].lower())
    for row in rows:
        row["cell_seconds"] = time.perf_counter() - t0
        row["cell_cpu_seconds"] = time.process_time() - cpu0
    return rows


class _Cell:
    """One cell's fits, each timed with its configuration (its steps and batch size), and
    the scores of the learners it reports: BC (fit 0), DAgger (fit ``rounds - 1``), BC at
    DAgger's query budget (fit ``rounds``)."""

    def __init__(self, task: Any, loss: str, bc: Any, seed: int) -> None:
        self.task, self.loss, self.bc, self.seed = task, loss, bc, seed
        self.proto = task.protocol
        self.warm = self.proto.round_steps is not None
        """each DAgger round continues the last fit for ``round_steps`` steps"""
        self.results: dict[int, dict] = {}
        self.fit_seconds: list[float] = []
        self.fit_configs: list = []

    def fit(self, learner: Learner, buf: DemonstrationBuffer):
        """What dagger does without ``train=``, timed; a chunked learner's fit adds every
        row's label chunk (and history) from the (relabelled) rows of its episode."""
        t = time.perf_counter()
        config = self.bc
        if self.warm and self.fit_seconds:  # its warm-up sized to this fit
            config = registry.fit_config(
                self.loss, replace(self.bc, num_steps=self.proto.round_steps)
            )
        out = fit_bc(learner, buf, config)
        self.fit_seconds.append(time.perf_counter() - t)
        self.fit_configs.append(config)
        return out

    def score(self, k: int, learner: Learner) -> None:
        """Score fit ``k``'s learner where the cell reports it."""
        if k in (0, self.proto.rounds - 1, self.proto.rounds):
            t = time.perf_counter()
            result = self.task.score(learner.policy, learner.exploration, self.seed)
            result.update(self.task.extras(learner, self.seed))
            result["eval_seconds"] = time.perf_counter() - t
            self.results[k] = result

    def matched(self, env, expert, count: int, learner: Learner) -> tuple:
        """``learner`` fitted on ``count`` rows of the expert's own episodes, for as many
        steps as DAgger's learner took in all (warm) or in its last fit."""
        last = self.fit_configs[-1].num_steps
        steps = sum(c.num_steps for c in self.fit_configs) if self.warm else last
        rows = _expert_rows(env, expert, count, self.task.max_steps(), self.seed)
        t = time.perf_counter()
        config = registry.fit_config(self.loss, replace(self.bc, num_steps=steps))
        fit = fit_bc(learner, rows, config)
        self.fit_seconds.append(time.perf_counter() - t)
        self.fit_configs.append(config)
        self.score(self.proto.rounds, learner)
        return learner, rows.shape[0], fit

    def rows(self, records: list[tuple], demo_rows: int, exploration: str) -> list[dict]:
        """The cell's rows: BC, DAgger (more than one round), BC at DAgger's queries."""
        rounds = self.proto.rounds
        algorithms = [("bc", 0)] + ([("dagger", rounds - 1)] if rounds > 1 else [])
        if len(records) > rounds:  # BC at DAgger's query budget
            algorithms.append(("bc_matched", rounds))
        rows = []
        for algorithm, k in algorithms:
            _, rows_trained, fit = records[k]
            configs = self.fit_configs
            rows.append(
                {
                    "task": self.task.name,
                    "loss": self.loss,
                    "seed": self.seed,
                    "algorithm": algorithm,
                    "exploration": exploration,
                    "rows_trained": rows_trained,
                    "demo_rows": demo_rows,
                    "final_loss": fit.final_loss,
                    "fit_seconds": self.fit_seconds[k],
                    # the gradient steps the reported learner took (warm: every fit so far)
                    "fit_steps": sum(c.num_steps for c in configs[: k + 1])
                    if self.warm and algorithm != "bc_matched"
                    else configs[k].num_steps,
                    "fit_batch": configs[k].batch_size,
                    **self.results[k],
                }
            )
            if self.proto.curve_points:
                rows[-1]["loss_curve"] = window_means(fit.losses, self.proto.curve_points)
        return rows


def window_means(losses: torch.Tensor, points: int) -> list[float]:
    """A fit's per-step losses as ``points`` means over consecutive windows (fewer when the
    fit took fewer steps)."""
    return [
        float(w.mean()) for w in torch.tensor_split(losses.double(), min(points, losses.numel()))
    ]


def _expert_rows(env, expert, count: int, max_steps: int, seed: int) -> TensorDictBase:
    """The first ``count`` rows of fresh expert-driven episodes (from starts of their own:
    the env re-seeded apart from the demonstrations'), for BC at a query budget."""
    env.set_seed(20_000 + seed)
    parts, have = [], 0
    while have < count:
        rows = rollout(env, as_actor(expert), 4, exploration=DET, max_steps=max_steps)
        rows.set(keys.EPISODE, rows.get(keys.EPISODE) + 4 * len(parts))
        parts.append(rows)
        have += rows.shape[0]
    return torch.cat(parts)[:count]


def plan(
    tasks: list[TaskDef], losses: list[str] | None, seeds: list[int], quick_mode: bool
) -> tuple[list[tuple], list[tuple]]:
    """The (task, loss, seed, quick) cells and (task, seed, quick) references of a run.

    A requested loss that applies to none of the tasks is refused naming the tasks'
    action kinds; one that applies to some of them runs there, and stderr names the
    tasks it does not apply to (was: dropped without a word, issue 44)."""
    cells, refs, applies = [], [], {name: [] for name in losses or []}
    for defn in tasks:
        spec = build(defn, quick_mode).spec()
        names = [n for n in registry.names(spec) if n != FOR_ENV]  # for_env: a network
        for name, where in applies.items():
            if name in names:
                where.append(defn.name)
        for seed in seeds:
            refs.append((defn, seed, quick_mode))
            cells += [(defn, n, seed, quick_mode) for n in names if losses is None or n in losses]
    task_names = [d.name for d in tasks]
    for name, where in applies.items():
        if not where:
            raise ValueError(
                f"--losses {name}: applies to none of the tasks {task_names} (it takes "
                f"{registry.get(name).actions} actions"
                + (
                    f" and a task's {', '.join(registry.get(name).requires)}"
                    if registry.get(name).requires
                    else ""
                )
                + ")"
            )
        if len(where) < len(tasks):
            skipped = [t for t in task_names if t not in where]
            print(f"loss_functions: {name} does not apply to {skipped}: runs on {where}",
                  file=sys.stderr)  # fmt: skip
    if not cells:
        raise ValueError(f"no loss applies to the tasks {task_names}")
    return cells, refs


def run(
    *,
    tasks: list[TaskDef],
    losses: list[str] | None,
    seeds: int | Sequence[int],
    quick_mode: bool,
    jobs: int = 1,
    modules: tuple[str, ...] = (),
    probe: Callable[[TensorDictBase], dict] | None = None,
) -> dict[str, Any]:
    """Every (loss, task, seed) cell and the expert/random references; returns the raw rows.

    ``seeds``: a count (seeds 0..n-1) or the seeds themselves (a cell's digits depend on
    its seed alone, so a run of seeds 1-4 extends a run of seed 0). ``probe``: each
    cell's (:func:`loss_cell`; a module-level function, so that workers can take it)."""
    seed_list = list(range(seeds)) if isinstance(seeds, int) else list(seeds)
    cells, refs = plan(tasks, losses, seed_list, quick_mode)
    if probe is not None:
        cells = [(*cell, probe) for cell in cells]
    rows, ref_rows = execute(cells, refs, jobs=jobs, modules=modules)
    protocols = {d.name: asdict(build(d, quick_mode).protocol) for d in tasks}
    definitions = {d.name: asdict(d) for d in tasks}
    return {"rows": rows, "references": ref_rows, "protocols": protocols, "tasks": definitions}


def execute(
    cells: list[tuple], refs: list[tuple], *, jobs: int = 1, modules: tuple[str, ...] = ()
) -> tuple[list[dict], list[dict]]:
    """Run ``cells`` (:func:`loss_cell`'s arguments) and ``refs`` (:func:`reference_cell`'s)
    in ``jobs`` processes; returns their rows, in the order given. :func:`run` plans them
    from task definitions; a benchmark with cells of its own (``metaworld_budgets.py``:
    a ladder of fit steps per loss) hands them here."""
    # the longest cells first (a rough cost), so that the last to finish are short; the
    # rows come back in the cells' own order
    schedule = sorted(range(len(cells)), key=lambda i: -_cost(*cells[i][:2]))
    t_start = time.perf_counter()

    def report(n: int, i: int, cell: list[dict]) -> None:
        print(
            f"[{n}/{len(cells)}] {cells[i][0].name} {cells[i][1]} seed {cells[i][2]}: "
            + " ".join(f"{r['algorithm']} {r['score']:.3f}" for r in cell)
            + f" (total {time.perf_counter() - t_start:.0f} s)",
            file=sys.stderr,
            flush=True,
        )

    done: dict[int, list[dict]] = {}
    if jobs > 1:
        # fresh workers every WORKER_CELLS cells: a worker's resident memory grew by about
        # 90 MB a cell on Meta-World (to 5.7 GB each after 14 minutes of ACT cells) and
        # is not given back to the system; a cell's digits depend on its seed alone.
        # multiprocessing's Pool, not ProcessPoolExecutor(max_tasks_per_child=): the
        # executor does not replace a retiring worker while tasks are queued and hangs
        # (CPython gh-115634); spawned workers import the modules that register losses
        spawn = multiprocessing.get_context("spawn")
        with spawn.Pool(
            jobs, maxtasksperchild=WORKER_CELLS, initializer=_import_all, initargs=(modules,)
        ) as pool:
            # one reference a task (chunksize=1): maxtasksperchild counts chunks, and
            # MT50's 150 references in chunks of 19 grew each worker to 5.4 GB
            ref_rows = [r for rows in pool.starmap(reference_cell, refs, chunksize=1) for r in rows]
            work = [(i, cells[i]) for i in schedule]
            for i, cell in pool.imap_unordered(_indexed_cell, work, chunksize=1):
                done[i] = cell
                report(len(done), i, cell)
            pool.close()  # let the workers exit (the with-block would terminate them)
            pool.join()
    else:
        ref_rows = [r for args in refs for r in reference_cell(*args)]
        for i in schedule:
            done[i] = loss_cell(*cells[i])
            report(len(done), i, done[i])
    return [r for i in range(len(cells)) for r in done[i]], ref_rows


def _import_all(modules: tuple[str, ...]) -> None:
    """A spawned worker's start: import the modules whose entries join the run."""
    for module in modules:
        importlib.import_module(module)


def _indexed_cell(item: tuple[int, tuple]) -> tuple[int, list[dict]]:
    i, args = item
    return i, loss_cell(*args)


_STEP_COST = {"act": 7, "diffusion_unet": 20}
"""a fit step's rough cost in MLP steps, where it differs (:func:`_cost`)"""


def _cost(defn: TaskDef, loss: str) -> float:
    """A rough relative cost of a cell (only the order the cells start in depends on it):
    its fit steps weighted by batch size; ACT's transformer step costs about seven MLP
    steps (measured: 25 ms at batch 128 against 3-4 ms at batch 256 on one thread), the
    U-Net of ``diffusion_unet`` about twenty (70 ms at batch 64: ``diffusion_policy.py``)."""
    p = defn.protocol
    per_step = max(p.bc.batch_size or 256, 256) / 256 * _STEP_COST.get(loss, 1)
    steps = p.bc.num_steps * p.rounds
    if p.round_steps is not None:
        steps = p.bc.num_steps + (p.rounds - 1) * p.round_steps
    return steps * per_step + 10 * p.eval_episodes

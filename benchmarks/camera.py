"""Cameras: BC throughput on 84x84 pixels, and BC vs DAgger from pixels with a state expert.

1. Throughput. ``fit_bc`` minibatch steps (batch 256) of ``build("for_env", ...)``'s CNN on
   uint8 ``[84, 84, 3]`` images (the default Nature CNN 32-64-64, MLP 256, a
   deterministic head on 2 bounded actions, MSE), against a plain torch loop of the same
   network (same layers, uint8 / 255 inside, Adam, MSE) on the same tensors. Samples/s,
   best of ``repeats`` (the two interleaved); the ratio is what compares across machines.
2. BC vs DAgger on :class:`imitrl.envs.pixel_tasks.PixelBalanceEnv` (hold a ball on an
   unstable hilltop; the learner sees a 32x32 image, the privileged expert
   ``u = clip(-8 p, -1, 1)`` reads the state ``p``). Per seed:

   a. one expert episode (100 steps) goes into a ``DemonstrationBuffer``;
   b. ``dagger`` fits a fresh CNN learner on it (round 0 = BC on the demonstration),
      then runs ``relabel_rounds`` rounds: roll the learner greedily on
      ``episodes_per_round`` lanes (beta = 0), label every visited state with the
      expert (from the state), aggregate, refit a fresh learner;
   c. "BC, matched": a fresh learner fitted on as many expert-driven rows as DAgger's
      last fit (the first rows of fresh expert episodes);
   d. every learner, the expert and a uniformly random policy play the same
      ``eval_episodes`` initial states (the eval env is re-seeded before each).

   Return = steps the ball stays in view (at most 100). Scores are normalised per seed:
   ``(R - R_random) / (R_expert - R_random)``. Success criterion: DAgger reaches
   ``threshold`` (0.9) within 5 rounds on at least 4 of 5 seeds while BC from the same
   demonstration stays clearly below.

    python benchmarks/camera.py --out benchmarks/results   # full run, results only
    python benchmarks/camera.py                            # full run, also the README block
    python benchmarks/camera.py --quick                    # smoke run, temporary directory
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import time
from dataclasses import dataclass
from functools import partial

import torch
import torch.nn.functional as F
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.data import Bounded

import _report
from _common import DET, reference_returns, returns, rollout, source
from imitrl import keys
from imitrl.algorithms import BCConfig, Constant, DAggerConfig, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.envs.pixel_tasks import Hilltop, PixelBalanceEnv, balance_expert
from imitrl.evaluation import t_interval
from imitrl.learners import ActorCritic, TaskSpec, build

NAME = "camera"
EVAL_SEED, SOURCE_SEED, MATCHED_SEED = 10_000, 1_000, 2_000
ACTION = Bounded(-1.0, 1.0, shape=(2,), dtype=torch.float32)


@dataclass(frozen=True)
class Config:
    """The whole run (part 1: throughput; part 2: the hilltop study)."""

    image: tuple[int, int] = (84, 84)
    """``(H, W)`` of the throughput images (3 channels, uint8)"""
    rows: int = 2048
    """rows of the throughput dataset (random images, random labels in [-1, 1])"""
    batch_size: int = 256
    """minibatch of the throughput fits"""
    timed_steps: int = 20
    """timed minibatch steps per throughput measurement"""
    repeats: int = 3
    """best of this many throughput measurements"""
    seeds: int = 5
    """training seeds of the study (seed s: demonstration env seed s, learner init s)"""
    relabel_rounds: int = 5
    """DAgger rounds after the BC fit"""
    episodes_per_round: int = 4
    """learner episodes relabelled per DAgger round (parallel lanes)"""
    pixels: tuple[int, int] = (32, 32)
    """``(H, W)`` of the hilltop image"""
    channels: tuple[int, ...] = (16, 32)
    """conv channels of the study's learner (kernel 3, stride 2 each)"""
    hidden: tuple[int, ...] = (64,)
    """MLP after the convolutions"""
    lr: float = 1e-3
    """Adam learning rate"""
    fit_steps: int = 400
    """Adam steps of every study fit"""
    fit_batch: int = 128
    """minibatch of every study fit"""
    eval_episodes: int = 50
    """greedy evaluation episodes per learner (one lane each, same initial states)"""
    threshold: float = 0.9
    """normalised score that counts as reaching the expert"""
    horizon: int = 100
    """steps of a hilltop episode"""


QUICK = Config(
    image=(36, 36),
    rows=64,
    batch_size=16,
    timed_steps=2,
    repeats=1,
    seeds=1,
    relabel_rounds=1,
    episodes_per_round=2,
    pixels=(16, 16),
    channels=(4,),
    hidden=(8,),
    fit_steps=3,
    fit_batch=16,
    eval_episodes=2,
    horizon=10,
)


# ------------------------------------------------------------------ 1. throughput
def throughput_data(cfg: Config) -> TensorDict:
    """Random uint8 images ``[rows, H, W, 3]``, a state column and labels in [-1, 1]."""
    g = torch.Generator().manual_seed(0)
    n = cfg.rows
    pixels = torch.randint(0, 256, (n, *cfg.image, 3), generator=g, dtype=torch.uint8)
    return TensorDict(
        {
            keys.PIXELS: pixels,
            keys.OBSERVATION: torch.zeros(n, 2),  # not read by the learner
            keys.EXPERT_ACTION: 2 * torch.rand(n, 2, generator=g) - 1,
        },
        batch_size=[n],
    )


def plain_cnn(cfg: Config) -> nn.Sequential:
    """The throughput learner's policy written in plain torch (Nature CNN, MLP 256, tanh)."""
    torch.manual_seed(0)
    side = (
        ((cfg.image[0] - 8) // 4 + 1 - 4) // 2 + 1 - 2,
        ((cfg.image[1] - 8) // 4 + 1 - 4) // 2 + 1 - 2,
    )
    return nn.Sequential(
        nn.Conv2d(3, 32, 8, stride=4), nn.ReLU(),
        nn.Conv2d(32, 64, 4, stride=2), nn.ReLU(),
        nn.Conv2d(64, 64, 3, stride=1), nn.ReLU(),
        nn.Flatten(), nn.Linear(64 * side[0] * side[1], 256), nn.ReLU(),
        nn.Linear(256, 2), nn.Tanh(),
    )  # fmt: skip


def plain_fit(cfg: Config, data: TensorDict) -> float:
    """Samples/s of a plain minibatch loop (rows without replacement, epoch after epoch)."""
    net = plain_cnn(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    pixels, labels = data[keys.PIXELS], data[keys.EXPERT_ACTION]
    n, g = pixels.shape[0], torch.Generator().manual_seed(0)
    perm, cursor = torch.randperm(n, generator=g), 0
    t0 = time.perf_counter()
    for _ in range(cfg.timed_steps):
        if cursor + cfg.batch_size > n:
            perm, cursor = torch.randperm(n, generator=g), 0
        idx = perm[cursor : cursor + cfg.batch_size]
        cursor += cfg.batch_size
        x = pixels[idx].float().div(255.0).movedim(-1, -3)  # [B, 3, H, W] in [0, 1]
        loss = F.mse_loss(net(x), labels[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return cfg.timed_steps * cfg.batch_size / (time.perf_counter() - t0)


def imitrl_fit(cfg: Config, data: TensorDict) -> float:
    """Samples/s of ``fit_bc`` with ``build("for_env", ...)``'s CNN (its defaults) on the same rows."""
    learner = build("for_env", TaskSpec.from_specs(None, ACTION, pixels=(*cfg.image, 3)), lr=1e-3)
    bc = BCConfig(num_steps=cfg.timed_steps, batch_size=cfg.batch_size)
    t0 = time.perf_counter()
    fit_bc(learner, data, bc)
    return cfg.timed_steps * cfg.batch_size / (time.perf_counter() - t0)


def throughput(cfg: Config, log) -> dict:
    data = throughput_data(cfg)
    # interleaved, so that load from elsewhere on a shared machine hits both alike
    runs = [(plain_fit(cfg, data), imitrl_fit(cfg, data)) for _ in range(cfg.repeats)]
    plain, lib = max(r[0] for r in runs), max(r[1] for r in runs)
    log(f"throughput: plain {plain:,.0f} samples/s, fit_bc {lib:,.0f} ({lib / plain:.2f}x)")
    return {"plain_samples_per_s": plain, "imitrl_samples_per_s": lib, "ratio": lib / plain}


# --------------------------------------------------------------- 2. the hilltop study
def hilltop(cfg: Config, lanes: int, seed: int) -> PixelBalanceEnv:
    batch = (lanes,) if lanes > 1 else ()
    hill = Hilltop(horizon=cfg.horizon)
    return PixelBalanceEnv(pixels=cfg.pixels, hill=hill, batch_size=batch, seed=seed)


def make_learner(env: PixelBalanceEnv, cfg: Config, seed: int) -> ActorCritic:
    """A fresh CNN learner of the image alone (the state is the expert's)."""
    return build("for_env", env, channels=cfg.channels, hidden=cfg.hidden, lr=cfg.lr, seed=seed)


def expert_rows(cfg: Config, seed: int, n: int) -> TensorDict:
    """The first ``n`` rows of fresh expert episodes (``episodes_per_round`` lanes)."""
    env, expert = hilltop(cfg, cfg.episodes_per_round, MATCHED_SEED + seed), balance_expert()
    chunks, have = [], 0
    while have < n:
        chunk = rollout(
            env, expert.as_actor(), cfg.episodes_per_round, exploration=DET, max_steps=cfg.horizon
        )
        chunks.append(chunk)
        have += chunk.shape[0]
    return torch.cat(chunks)[:n]


def run_seed(cfg: Config, seed: int) -> dict:
    """One seed: BC, DAgger per round, BC with matched samples, normalised scores."""
    expert, limit = balance_expert(), cfg.horizon
    bc = BCConfig(num_steps=cfg.fit_steps, batch_size=cfg.fit_batch, seed=seed)

    # -- the demonstration: one expert episode
    demo_env = hilltop(cfg, 1, seed)
    buffer = DemonstrationBuffer(action_spec=demo_env.action_spec_unbatched)
    buffer.extend(rollout(demo_env, expert.as_actor(), 1, exploration=DET, max_steps=limit))

    # -- evaluation on the same initial states for every policy of this seed
    n, eval_seed = cfg.eval_episodes, EVAL_SEED + seed
    eval_env = hilltop(cfg, n, eval_seed)
    ref = reference_returns(eval_env, expert, n, seed=eval_seed, max_steps=limit)
    expert_return, random_return = float(ref["expert"].mean()), float(ref["random"].mean())

    def score(policy: TensorDictModuleBase) -> float:
        eval_env.set_seed(eval_seed)
        return float(returns(eval_env, policy, n, exploration=DET, max_steps=limit).mean())

    def normalise(r: float) -> float:
        gap = expert_return - random_return
        return (r - random_return) / gap if gap != 0 else float("nan")

    # -- DAgger; its round 0 is BC on the demonstration
    source_env = hilltop(cfg, cfg.episodes_per_round, SOURCE_SEED + seed)
    learner_of = partial(make_learner, source_env, cfg, seed)
    dagger_returns: list[float] = []
    t0 = time.perf_counter()
    result = dagger(
        source(source_env, exploration=DET, max_steps=limit),
        expert,
        learner_of,
        buffer,
        DAggerConfig(
            rounds=cfg.relabel_rounds + 1,
            episodes_per_round=cfg.episodes_per_round,
            beta=Constant(0.0),
            bc=bc,
            seed=seed,
        ),
        on_fit=lambda k, learner: dagger_returns.append(score(learner.policy)),
    )
    dagger_s = time.perf_counter() - t0
    rows = [r.rows_trained for r in result.rounds]

    # -- BC with as many expert rows as DAgger's last fit used
    matched = learner_of()
    fit_bc(matched, expert_rows(cfg, seed, rows[-1]), bc)
    matched_return = score(matched.policy)

    scores = [normalise(r) for r in dagger_returns]
    reached = [k for k in range(1, len(scores)) if scores[k] >= cfg.threshold]
    return {
        "seed": seed,
        "expert_return": expert_return,
        "random_return": random_return,
        "dagger_returns": dagger_returns,
        "dagger_scores": scores,
        "rows": rows,
        "bc_score": scores[0],
        "bc_matched_score": normalise(matched_return),
        "first_round_reached": reached[0] if reached else None,
        "dagger_seconds": dagger_s,
    }


def study(cfg: Config, log) -> dict:
    seeds = []
    for seed in range(cfg.seeds):
        record = run_seed(cfg, seed)
        seeds.append(record)
        log(
            f"hilltop seed {seed}: bc {record['bc_score']:.2f} dagger "
            f"{[round(x, 2) for x in record['dagger_scores']]} matched "
            f"{record['bc_matched_score']:.2f} rows {record['rows']} "
            f"({record['dagger_seconds']:.0f} s)"
        )
    reached = sum(r["first_round_reached"] is not None for r in seeds)
    return {"seeds": seeds, "reached": reached}


# ------------------------------------------------------------------------ report
def markdown(results: dict, cfg: Config) -> str:
    tp = results["throughput"]
    h, w = cfg.image
    part1 = _report.table(
        ["what", "samples/s", "x plain"],
        [
            [f"CNN {h}x{w}x3 uint8, plain torch loop", f"{tp['plain_samples_per_s']:,.0f}", "1.00"],
            [f"CNN {h}x{w}x3 uint8, imitrl fit_bc", f"{tp['imitrl_samples_per_s']:,.0f}",
             f"{tp['ratio']:.2f}"],
        ],
    )  # fmt: skip
    seeds = results["study"]["seeds"]
    rounds = len(seeds[0]["dagger_scores"]) - 1
    rows = [
        [
            r["seed"],
            f"{r['expert_return']:.1f}",
            f"{r['random_return']:.1f}",
            f"{r['bc_score']:.2f}",
            *[f"{x:.2f}" for x in r["dagger_scores"][1:]],
            "-" if r["first_round_reached"] is None else r["first_round_reached"],
            f"{r['bc_matched_score']:.2f} ({r['rows'][-1]} rows)",
        ]
        for r in seeds
    ]
    part2 = _report.table(
        ["seed", "expert", "random", "BC", *[f"DAgger {k}" for k in range(1, rounds + 1)],
         f"first >= {cfg.threshold}", "BC, matched"],
        rows,
    )  # fmt: skip
    bc = _report.fmt_ci(t_interval([r["bc_score"] for r in seeds]))
    last = _report.fmt_ci(t_interval([r["dagger_scores"][-1] for r in seeds]))
    return (
        f"BC minibatch throughput, batch {cfg.batch_size}, {cfg.timed_steps} steps, best of "
        f"{cfg.repeats}:\n\n{part1}\n\nBC vs DAgger on the hilltop ({cfg.pixels[0]}x"
        f"{cfg.pixels[1]} pixels, state expert), normalised scores per seed: DAgger reached "
        f"{cfg.threshold} within {rounds} rounds on {results['study']['reached']} of "
        f"{len(seeds)} seeds; BC {bc}, DAgger's last round {last} (mean [95% CI]). Total wall "
        f"time {results['seconds'] / 60:.1f} min.\n\n{part2}\n"
    )


def figure(results: dict, cfg: Config, path) -> None:
    """Normalised score per DAgger round (round 0 = BC), one line per seed; x: BC with as
    many expert rows as DAgger's last fit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from imitrl.plotting import save_figure

    fig, ax = plt.subplots(figsize=(5, 3.2))
    for r in results["study"]["seeds"]:
        last = len(r["dagger_scores"]) - 1
        (line,) = ax.plot(range(last + 1), r["dagger_scores"], marker="o", alpha=0.8,
                          label=f"seed {r['seed']}")  # fmt: skip
        ax.plot([last + 0.25], [r["bc_matched_score"]], marker="x", color=line.get_color())
    ax.axhline(cfg.threshold, color="k", ls="--", lw=1, label=f"{cfg.threshold}")
    ax.set_xlabel("DAgger round (0: BC on the demo; x: BC, matched rows)", fontsize=9)
    ax.set_ylabel("normalised score")
    ax.set_title("Hilltop from pixels, privileged state expert", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)  # every label on the canvas
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)

    def log(s: str) -> None:
        print(s, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    results = {"config": dataclasses.asdict(cfg), "throughput": throughput(cfg, log)}
    results["study"] = study(cfg, log)
    results["seconds"] = time.perf_counter() - t0
    figure(results, cfg, _report.results_dir(out_dir) / f"{NAME}.png")
    md = markdown(results, cfg)
    print("results:", _report.write(NAME, results, md, out_dir=out_dir))
    print(md)
    return results


if __name__ == "__main__":
    main()

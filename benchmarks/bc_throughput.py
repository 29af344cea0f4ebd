"""BC update throughput against a plain-torch loop, and DAgger rounds per second.

1. MLP minibatch fit (the target: imitrl >= 0.95x the plain loop's samples/s): a
   categorical MLP on vector observations, Adam, cross-entropy, minibatches drawn
   without replacement. imitrl runs `fit_bc` with `build("for_env", ...)`'s MLP (observations
   normalised inside the network, the library's default) through the learner's loss;
   the plain loop is the same network, normalisation included, and optimizer written
   directly.
2. Tabular full-batch fit of the section's size (FrozenLake demonstrations, 200 Adam
   steps; the target: imitrl >= 0.9x the plain loop's steps/s). Both clocks start after
   the network and its optimizer (the learner) are built; fit_bc's own checks and its
   distinct-pair weighting are inside its time.
3. DAgger on slippery FrozenLake (4 rounds, 3 relabelled episodes per round, 200-step
   fits): rounds per second on the batched TabularEnv and on gymnasium's stream.

    python benchmarks/bc_throughput.py              # full run, refreshes README
    python benchmarks/bc_throughput.py --quick      # smoke run, into a temporary directory
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torch import nn

import _report
from _common import DET, lake, rollout, source
from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.envs import GymnasiumStream, GymnasiumStreamSource, TabularEnv
from imitrl.learners import TaskSpec, build
from imitrl.policies import BetaMixer, Expert, behaviour_policy
from imitrl.tabular import greedy

NAME = "bc_throughput"


@dataclass(frozen=True)
class Config:
    obs_dim: int = 16
    """observation size of the MLP task"""
    num_actions: int = 4
    """actions of the MLP task"""
    hidden: tuple[int, ...] = (256, 256)
    """hidden layers of the MLP"""
    rows: int = 50_000
    """rows in the MLP dataset"""
    batch_size: int = 256
    """minibatch size"""
    mlp_steps: int = 3_000
    """timed minibatch steps"""
    tabular_steps: int = 200
    """full-batch steps of the tabular fit"""
    dagger_runs: int = 5
    """DAgger runs timed (4 rounds each)"""
    repeats: int = 3
    """best of this many repeats"""
    tabular_repeats: int = 15
    """best of this many repeats of the tabular fits (a fraction of a second each)"""


QUICK = Config(
    rows=2_000, mlp_steps=30, tabular_steps=20, dagger_runs=1, repeats=1, tabular_repeats=1
)


def mlp_task(cfg: Config) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(cfg.rows, cfg.obs_dim, generator=g)
    W = torch.randn(cfg.obs_dim, cfg.num_actions, generator=g)
    return TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: (obs @ W).argmax(-1)}, [cfg.rows])


class Standardize(nn.Module):
    """``(x - mean) / std`` with the data's statistics, as the library's normaliser."""

    def __init__(self, x: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("loc", x.double().mean(0).float())
        self.register_buffer("scale", x.double().std(0, correction=0).float())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.loc) / self.scale


def plain_mlp(cfg: Config, data: TensorDict) -> float:
    torch.manual_seed(0)
    sizes = [cfg.obs_dim, *cfg.hidden, cfg.num_actions]
    layers: list[nn.Module] = [Standardize(data[keys.OBSERVATION])]
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(nn.Tanh())
    net = nn.Sequential(*layers)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, foreach=True)  # as ActorCritic's
    obs, act = data[keys.OBSERVATION], data[keys.EXPERT_ACTION]
    n, g = obs.shape[0], torch.Generator().manual_seed(0)
    perm, cursor = torch.randperm(n, generator=g), 0
    t0 = time.perf_counter()
    for _ in range(cfg.mlp_steps):
        if cursor + cfg.batch_size > n:
            perm, cursor = torch.randperm(n, generator=g), 0
        idx = perm[cursor : cursor + cfg.batch_size]
        cursor += cfg.batch_size
        loss = F.cross_entropy(net(obs[idx]), act[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return cfg.mlp_steps * cfg.batch_size / (time.perf_counter() - t0)


def imitrl_mlp(cfg: Config, data: TensorDict) -> float:
    learner = build(
        "for_env", TaskSpec.from_specs(cfg.obs_dim, cfg.num_actions), hidden=cfg.hidden, lr=1e-3
    )
    t0 = time.perf_counter()
    fit_bc(learner, data, BCConfig(num_steps=cfg.mlp_steps, batch_size=cfg.batch_size))
    return cfg.mlp_steps * cfg.batch_size / (time.perf_counter() - t0)


def imitrl_mlp_from_buffer(cfg: Config, data: TensorDict) -> float:
    """Minibatches through TorchRL's ReplayBuffer.sample (the buffer's own sampler)."""
    n = data.shape[0]
    rows = data.clone()
    rows.set(keys.ACTION, rows[keys.EXPERT_ACTION].clone())
    rows.set(keys.EXPERT_EXECUTED, torch.ones(n, dtype=torch.bool))
    rows.set(keys.EPISODE, torch.arange(n))
    rows.set(keys.ROUND, torch.zeros(n, dtype=torch.int64))
    rows.set(keys.STEP, torch.zeros(n, dtype=torch.int64))
    buf = DemonstrationBuffer(
        capacity=n, batch_size=cfg.batch_size, generator=torch.Generator().manual_seed(0)
    )
    buf.extend(rows)
    learner = build(
        "for_env", TaskSpec.from_specs(cfg.obs_dim, cfg.num_actions), hidden=cfg.hidden, lr=1e-3
    )
    learner.prepare(rows)  # what fit_bc does first: fit the observation normaliser
    t0 = time.perf_counter()
    for _ in range(cfg.mlp_steps):
        loss = learner.loss.objective(buf.sample())
        learner.opt_pi.zero_grad(set_to_none=True)
        loss.backward()
        learner.opt_pi.step()
    return cfg.mlp_steps * cfg.batch_size / (time.perf_counter() - t0)


def tabular_fits(cfg: Config) -> tuple[float, float, int]:
    mdp, Q = lake()
    env = TabularEnv(mdp, batch_size=(3,), seed=0)
    rows = rollout(
        env, Expert.from_table(greedy(Q)).as_actor(), 3, exploration=DET, max_steps=10_000
    )
    obs, act = rows[keys.OBSERVATION], rows[keys.EXPERT_ACTION]
    policy = nn.Embedding(16, 4)
    nn.init.zeros_(policy.weight)
    opt = torch.optim.Adam(policy.parameters(), lr=0.1)
    t0 = time.perf_counter()
    for _ in range(cfg.tabular_steps):
        loss = -torch.log_softmax(policy(obs), -1).gather(-1, act[:, None]).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    plain = cfg.tabular_steps / (time.perf_counter() - t0)
    learner = build("cross_entropy", TaskSpec(action=4, num_states=16))
    t0 = time.perf_counter()
    fit_bc(learner, rows, BCConfig(num_steps=cfg.tabular_steps, batch_size=None))
    lib = cfg.tabular_steps / (time.perf_counter() - t0)
    return plain, lib, rows.shape[0]


def dagger_rounds(cfg: Config, source_kind: str) -> float:
    mdp, Q = lake()
    expert = Expert.from_table(greedy(Q))
    rounds = 0
    t0 = time.perf_counter()
    for seed in range(cfg.dagger_runs):
        if source_kind == "tabular_env":
            env = TabularEnv(mdp, batch_size=(3,), seed=seed)
            demos = rollout(env, expert.as_actor(), 3, exploration=DET, max_steps=10_000)
            episodes = source(env, exploration=None, max_steps=100_000)
        else:
            episodes = GymnasiumStreamSource(mdp, GymnasiumStream(seed))
            demos = episodes.collect(
                behaviour_policy(expert, None, BetaMixer(1.0)), 3, round_index=0, first_episode=0
            )
        buf = DemonstrationBuffer(num_states=16)
        buf.extend(demos)
        res = dagger(
            episodes,
            expert,
            lambda: build("cross_entropy", TaskSpec(action=4, num_states=16)),
            buf,
            DAggerConfig(
                rounds=4, episodes_per_round=3, bc=BCConfig(num_steps=200, batch_size=None)
            ),
        )
        rounds += len(res.rounds)
    return rounds / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> dict:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    data = mlp_task(cfg)
    mlp = [(plain_mlp(cfg, data), imitrl_mlp(cfg, data)) for _ in range(cfg.repeats)]  # alternated
    plain, lib = max(m[0] for m in mlp), max(m[1] for m in mlp)
    lib_rb = max(imitrl_mlp_from_buffer(cfg, data) for _ in range(cfg.repeats))
    tab = [tabular_fits(cfg) for _ in range(cfg.tabular_repeats)]
    tab_plain, tab_lib, tab_rows = max(t[0] for t in tab), max(t[1] for t in tab), tab[0][2]
    dg_env = max(dagger_rounds(cfg, "tabular_env") for _ in range(cfg.repeats))
    dg_stream = max(dagger_rounds(cfg, "stream") for _ in range(cfg.repeats))
    rows = [
        ["MLP minibatch fit, plain torch loop", f"{plain:,.0f} samples/s", "1.00"],
        ["MLP minibatch fit, imitrl fit_bc", f"{lib:,.0f} samples/s", f"{lib / plain:.2f}"],
        [
            "MLP minibatch fit, TorchRL ReplayBuffer.sample + loss",
            f"{lib_rb:,.0f} samples/s",
            f"{lib_rb / plain:.2f}",
        ],
        [
            f"tabular full-batch fit ({tab_rows} rows), plain torch",
            f"{tab_plain:,.0f} steps/s",
            "1.00",
        ],
        [
            f"tabular full-batch fit ({tab_rows} rows), imitrl fit_bc",
            f"{tab_lib:,.0f} steps/s",
            f"{tab_lib / tab_plain:.2f}",
        ],
        ["DAgger rounds, batched TabularEnv", f"{dg_env:.1f} rounds/s", ""],
        ["DAgger rounds, gymnasium stream", f"{dg_stream:.1f} rounds/s", ""],
    ]
    for r in rows:
        print(" | ".join(r))
    md = (
        f"MLP {cfg.obs_dim}-{'-'.join(map(str, cfg.hidden))}-{cfg.num_actions} (observations "
        f"normalised), batch {cfg.batch_size}, {cfg.mlp_steps} steps; best of {cfg.repeats}. "
        f"Tabular: best of {cfg.tabular_repeats}. Targets: imitrl fit_bc >= 0.95x plain "
        "(MLP), >= 0.9x (tabular).\n\n" + _report.table(["what", "throughput", "x plain"], rows)
    )
    payload = {
        "config": cfg.__dict__,
        "mlp_plain_samples_per_s": plain,
        "mlp_imitrl_samples_per_s": lib,
        "mlp_replay_buffer_samples_per_s": lib_rb,
        "ratio": lib / plain,
        "tabular_plain_steps_per_s": tab_plain,
        "tabular_imitrl_steps_per_s": tab_lib,
        "tabular_ratio": tab_lib / tab_plain,
        "dagger_rounds_per_s_tabular_env": dg_env,
        "dagger_rounds_per_s_stream": dg_stream,
    }
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()

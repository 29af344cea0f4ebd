"""The FrozenLake study as a plain gymnasium + numpy script (torch only for the fits).

This is the baseline `imitrl frozenlake` is timed against: the section's code written
out directly (one gymnasium env stepped in Python, numpy tables, a torch embedding
fitted with Adam as the section does), running the same experiments, exercises and
figures with the same protocol and seeds. It prints the same numbers as the library's
faithful protocol (main blocks and exercises alike), so it doubles as an independent
cross-check.

    python benchmarks/frozenlake_plain.py --out /tmp/plain [--no-exercises]
    python benchmarks/frozenlake_plain.py --quick     # no exercises, figures to a temporary dir

It writes only figures (to ``--out``, by default a new temporary directory), never
``benchmarks/README.md`` or ``benchmarks/results/``.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
from torch import nn

torch.set_num_threads(1)
t_start = time.perf_counter()
parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", type=Path, default=None, help="figures (default: a temporary dir)")
parser.add_argument("--no-exercises", action="store_true", help="skip the exercises")
parser.add_argument("--quick", action="store_true", help="smoke run: --no-exercises")
args = parser.parse_args()
if args.out is None:
    args.out = Path(tempfile.mkdtemp(prefix="frozenlake_plain-"))
    print(f"figures go to {args.out}")
args.out.mkdir(parents=True, exist_ok=True)
args.no_exercises = args.no_exercises or args.quick

# ----------------------------------------------------------------- the expert
gamma = 0.95
env = gym.make("FrozenLake-v1", is_slippery=True)
U = env.unwrapped
S, A, T_LIMIT = 16, 4, env.spec.max_episode_steps
P = np.zeros((S, A, S))
r = np.zeros((S, A))
for s in range(S):
    for a in range(A):
        for p, s2, rew, _ in U.P[s][a]:
            P[s, a, s2] += p
            r[s, a] += p * rew
V = np.zeros(S)
for _ in range(1000):
    V = (r + gamma * P @ V).max(axis=1)
pi_star = (r + gamma * P @ V).argmax(axis=1)
terminal = np.array([c in b"GH" for c in U.desc.ravel()])
goal = np.array([c == b"G" for c in U.desc.ravel()])


def exact_success(table, T=T_LIMIT):
    d = np.eye(S)[0]
    Pp = P[np.arange(S), table]
    for _ in range(T):
        d = d @ Pp
    return d[goal].sum()


def distributions(table, T=T_LIMIT):
    d = [np.eye(S)[0]]
    Pp = P[np.arange(S), table]
    for _ in range(T):
        d.append(d[-1] @ Pp)
    return np.array(d)


def demonstrations(num_episodes):
    states, actions = [], []
    for _ in range(num_episodes):
        s, done = env.reset()[0], False
        while not done:
            states.append(s)
            actions.append(int(pi_star[s]))
            s, _, term, trunc, _ = env.step(actions[-1])
            done = term or trunc
    return np.array(states), np.array(actions)


def evaluate(policy, num_episodes):
    total = 0.0
    for _ in range(num_episodes):
        s, done = env.reset()[0], False
        while not done:
            s, rew, term, trunc, _ = env.step(policy(s))
            done = term or trunc
            total += rew
    return total / num_episodes


def clone(states, actions, num_steps=200):
    policy = nn.Embedding(S, A)
    nn.init.zeros_(policy.weight)
    opt = torch.optim.Adam(policy.parameters(), lr=0.1)
    obs, act = torch.as_tensor(states), torch.as_tensor(actions)
    for _ in range(num_steps):
        loss = -torch.log_softmax(policy(obs), -1).gather(-1, act[:, None]).squeeze(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return policy, loss.item()


def greedy(policy):
    with torch.no_grad():
        return policy.weight.argmax(dim=1).numpy()


def relabel(table, num_episodes):
    visited = []
    for _ in range(num_episodes):
        s, done = env.reset()[0], False
        while not done:
            visited.append(s)
            s, _, term, trunc, _ = env.step(int(table[s]))
            done = term or trunc
    visited = np.array(visited, dtype=np.int64)
    return visited, pi_star[visited]


def dagger(demo_s, demo_a, rounds=4, episodes=3, steps=200, on_fit=None, corrupt=None):
    agg_s, agg_a = demo_s, demo_a
    for k in range(rounds):
        policy, _ = clone(agg_s, agg_a, steps)
        table = greedy(policy)
        if on_fit is not None:
            on_fit(k, table, agg_s.size)
        if k + 1 < rounds:
            new_s, new_a = relabel(table, episodes)
            if corrupt is not None:
                new_a = corrupt(new_a)
            agg_s, agg_a = np.concatenate([agg_s, new_s]), np.concatenate([agg_a, new_a])
    return table, agg_s.size


print(
    "1. expert:",
    pi_star.tolist(),
    f"V*(0) = {V[0]:.6f}, exact success {exact_success(pi_star):.6f}",
)
env.reset(seed=0)
demo_s, demo_a = demonstrations(3)
print(
    f"{demo_s.size} state-action pairs from 3 expert episodes, covering {np.unique(demo_s).size} of 11 reachable states"
)
bc, nll = clone(demo_s, demo_a)
print(f"cross-entropy on the demonstrations after the fit: {nll:.3f}")
for s in (9, 3):
    with torch.no_grad():
        probs = torch.softmax(bc(torch.tensor([s])), -1)[0].numpy()
    print(f"clone pi(.|s={s}): {np.round(probs, 3)}")


def act_greedy(s, rng=None):
    with torch.no_grad():
        return int(bc(torch.as_tensor(s)).argmax())


env.reset(seed=1)
expert_rate = evaluate(lambda s: int(pi_star[s]), 1000)
clone_rate = evaluate(act_greedy, 1000)
clone_table = greedy(bc)
mistakes = sum(act_greedy(s) != a for s, a in zip(demo_s, demo_a))
print(f"mistakes on the {demo_s.size} demonstration pairs: {mistakes}")
print(
    f"success rate: expert {expert_rate:.1%}, clone {clone_rate:.1%}  (exact {exact_success(pi_star):.2%}, {exact_success(clone_table):.2%})"
)

env.reset(seed=2)
sweep = {}
for n in [1, 3, 10]:
    rates, exact = [], []
    for _ in range(10):
        policy, _ = clone(*demonstrations(n), num_steps=50)
        tab = greedy(policy)
        rates.append(evaluate(lambda s, tab=tab: int(tab[s]), 300))
        exact.append(exact_success(tab))
    rates = np.sort(np.array(rates))
    sweep[n] = (rates, np.array(exact))
    print(
        f"{n:>2} episodes: median success {np.median(rates):.0%}, worst {rates[0]:.0%}, over ten datasets"
    )

fig, axes = plt.subplots(1, 2, figsize=(10, 4))
for ax, (eps, T_max) in zip(axes, [(0.05, 10), (0.01, 64)]):
    rng = np.random.default_rng(3)
    wrong = rng.random((20000, T_max)) < eps
    T = np.arange(1, T_max + 1)
    gap_bc = T - np.cumprod(~wrong, axis=1).cumsum(axis=1).mean(axis=0)
    gap_rec = T - (~wrong).cumsum(axis=1).mean(axis=0)
    exact_bc = T - np.cumsum((1 - eps) ** T)
    for y, label in [
        (gap_bc, "cloned"),
        (eps * T**2 / 2, "eps T^2/2"),
        (gap_rec, "recovering"),
        (eps * T, "eps T"),
    ]:
        ax.plot(T, y, label=label)
    ax.plot(T, exact_bc, "k:", label="cloned (exact)")
    ax.set(xscale="log", yscale="log", xlabel="horizon T", ylabel="return lost to the expert")
    ax.legend()
    print(
        f"lost return at T={T_max}: cloned {gap_bc[-1]:.2f} (eps T^2/2 = {eps * T_max**2 / 2:.2f}), recovering {gap_rec[-1]:.2f} (eps T = {eps * T_max:.2f}); exact {exact_bc[-1]:.3f}"
    )
fig.savefig(args.out / "chain.png", bbox_inches="tight")  # no label cut off
plt.close(fig)

d_exp, d_clo = distributions(pi_star, 20), distributions(clone_table, 20)
for t in (3, 5, 10, 20):
    print(f"after {t:>2} steps: total variation {0.5 * np.abs(d_exp[t] - d_clo[t]).sum():.3f}")
print(
    f"mass in the hole at s=12 after 20 steps: expert {d_exp[20][12]:.3f}, clone {d_clo[20][12]:.3f}"
)
fig, axes = plt.subplots(1, 2, figsize=(9, 4))
for ax, occ, tab, title in zip(
    axes, [d_exp[1:].mean(0), d_clo[1:].mean(0)], [pi_star, clone_table], ["expert", "clone"]
):
    ax.imshow(occ.reshape(4, 4), cmap="Blues")
    for s in range(S):
        if not terminal[s]:
            dx, dy = {0: (-1, 0), 1: (0, 1), 2: (1, 0), 3: (0, -1)}[int(tab[s])]
            ax.arrow(s % 4, s // 4, 0.3 * dx, 0.3 * dy, head_width=0.15)
    ax.set_title(f"{title} occupancy")
fig.savefig(args.out / "occupancy.png", bbox_inches="tight")  # no label cut off
plt.close(fig)

env.reset(seed=4)
dagger_rates = []


def on_fit(k, table, pairs):
    rate = evaluate(lambda s: int(table[s]), 1000)
    dagger_rates.append(rate)
    print(
        f"round {k}: trained on {pairs:>3} pairs, success rate {rate:.1%}  (exact {exact_success(table):.2%})"
    )


dagger(demo_s, demo_a, on_fit=on_fit)
fig, ax = plt.subplots()
ax.plot(dagger_rates, "o-")
ax.set(xlabel="DAgger round", ylabel="success rate")
fig.savefig(args.out / "dagger.png", bbox_inches="tight")  # no label cut off
plt.close(fig)

if not args.no_exercises:
    live = ~terminal
    d = distributions(pi_star)[:-1]
    expert_states = (d * live).sum(0) / (d * live).sum()
    # Exercise 2: return against N
    env.reset(seed=5)
    for N in (5, 20, 100, 500):
        succ, agree = [], []
        for _ in range(10):
            tab = greedy(clone(*demonstrations(N), num_steps=50)[0])
            succ.append(exact_success(tab))
            agree.append((expert_states * (tab == pi_star)).sum())
        print(
            f"N={N:>3}: exact success {np.mean(succ):.3f}, agreement on expert's states {np.mean(agree):.4f}"
        )
    # Exercise 3: per-state error vs visitation
    env.reset(seed=6)
    errors = np.zeros(S)
    for _ in range(50):
        errors += greedy(clone(*demonstrations(3), num_steps=50)[0]) != pi_star
    errors /= 50
    fig, ax = plt.subplots()
    ax.semilogx(np.maximum(expert_states, 1e-4), errors, "o")
    fig.savefig(args.out / "ex_state_errors.png", bbox_inches="tight")  # no label cut off
    plt.close(fig)
    print("per-state error:", np.round(errors, 2).tolist())
    # Exercise 4: equal query budget
    env.reset(seed=7)
    mean_len = (1 - distributions(pi_star)[:-1][:, terminal].sum(1)).sum()
    dg, bcb = [], []
    for _ in range(10):
        ds, da = demonstrations(3)
        table, budget = dagger(ds, da, steps=50)
        dg.append(exact_success(table))
        bs, ba = [], []
        while sum(x.size for x in bs) < budget:
            missing = budget - sum(x.size for x in bs)
            s_, a_ = demonstrations(max(1, math.ceil(missing / (1 + mean_len) * 1.2)))
            bs.append(s_)
            ba.append(a_)
        bs, ba = np.concatenate(bs)[:budget], np.concatenate(ba)[:budget]
        bcb.append(exact_success(greedy(clone(bs, ba, num_steps=50)[0])))
    print(f"equal budget: DAgger {np.mean(dg):.3f}, BC {np.mean(bcb):.3f}")
    # Exercise 5: corrupted labels
    env.reset(seed=8)
    gen = torch.Generator().manual_seed(8)

    def corrupt(labels):
        labels = torch.as_tensor(labels).clone()
        m = round(0.1 * labels.numel())
        if m:
            idx = torch.randperm(labels.numel(), generator=gen)[:m]
            labels[idx] = (labels[idx] + torch.randint(1, A, (m,), generator=gen)) % A
        return labels.numpy()

    res = {"bc": [], "bc_bad": [], "dg": [], "dg_bad": []}
    for _ in range(10):
        ds, da = demonstrations(3)
        bad = corrupt(da)
        res["bc"].append(exact_success(greedy(clone(ds, da, 50)[0])))
        res["bc_bad"].append(exact_success(greedy(clone(ds, bad, 50)[0])))
        res["dg"].append(exact_success(dagger(ds, da, steps=50)[0]))
        res["dg_bad"].append(exact_success(dagger(ds, bad, steps=50, corrupt=corrupt)[0]))
    print("corruption:", {k: round(float(np.mean(v)), 3) for k, v in res.items()})

print(f"wall time: {time.perf_counter() - t_start:.1f} s")

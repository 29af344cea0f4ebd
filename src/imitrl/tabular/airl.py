"""Exact tabular AIRL (Fu, Luo and Levine 2018) on a :class:`TabularMDP`.

Adversarial inverse RL learns a reward ``g(s)`` on the state acted in and a shaping
potential ``h(s)``; the discriminator reads

    ``D(s, a) = exp(f(s, a)) / (exp(f(s, a)) + pi(a|s))``,
    ``f(s, a) = g(s) + gamma * sum_s' P(s'|s, a) h(s') - h(s)``,

and the generator ``pi`` is soft-optimal (entropy weight 1) for the reward ``f``, which
is what maximising ``log D - log(1 - D) = f - log pi`` asks of it. Everything here is
exact on the MDP's tensors: the generator's discounted occupancy solves a linear system,
the discriminator's logistic loss is a sum over state-action pairs weighted by the two
occupancies (no sampling), and nothing is random. The shaping term is taken in
expectation over the known kernel (the tabular, model-based form of AIRL's
``gamma h(s') - h(s)``); with it, ``f = log pi_E`` is reachable, and the game's fixed point
``pi = pi_E``, ``f = log pi_E`` pins ``g`` to the demonstrator's reward up to a constant
whenever the kernel lets actions' expected potentials differ (checked on FrozenLake:
the map from ``(g, h)`` to ``f`` has a one-dimensional kernel, the constant).

The setting is AIRL's own: infinite horizon, discount ``gamma < 1``, terminal states
absorbing. A terminal state offers no choice (its rows are self-loops), so it takes a
single action: no entropy accrues there and ``log pi = 0`` in its logit. The
demonstrator is Boltzmann-rational (:func:`boltzmann_policy`: soft-optimal for
``beta`` times the MDP's reward); a greedy expert's zero-probability actions have no
finite ``f``, and its reward is not identified.

Reward transfer (the reason AIRL exists): ``g`` is a reward of the state alone, so it
can be planned against under another kernel (:func:`plan`), where ``f`` carries the
source kernel's shaping and a reward on the state entered (MaxEnt IRL's, section 8)
may carry it too.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from imitrl.tabular.mdp import TabularMDP
from imitrl.tabular.policy import kernel_under
from imitrl.tabular.sampling import OutcomeSampler

__all__ = [
    "AIRLResult",
    "airl",
    "boltzmann_policy",
    "discounted_occupancy",
    "empirical_occupancy",
    "plan",
    "sample_episodes",
    "shaped_reward",
    "soft_bellman",
]


def _gamma(mdp: TabularMDP, gamma: float | None) -> float:
    g = mdp.gamma if gamma is None else float(gamma)
    if not 0.0 < g < 1.0:
        raise ValueError(f"AIRL needs a discount in (0, 1) (an infinite horizon), got {g}")
    return g


def soft_bellman(
    mdp: TabularMDP,
    reward: torch.Tensor,
    gamma: float,
    v: torch.Tensor | None = None,
    sweeps: int = 1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``sweeps`` soft Bellman backups of ``reward`` ``[S, A]`` from ``v`` (zeros).

    ``Q(s, a) = reward(s, a) + gamma sum_s' P(s'|s, a) V(s')``; ``V(s) = log sum_a
    exp Q(s, a)`` on live states and ``Q(s, .)``'s common value on terminal ones (a single
    action). Returns ``(q [S, A], v [S])``.
    """
    v = torch.zeros(mdp.num_states, dtype=torch.float64) if v is None else v
    q = reward
    for _ in range(sweeps):
        q = reward + gamma * (mdp.P @ v)
        v = torch.where(mdp.terminal, q.mean(-1), torch.logsumexp(q, dim=-1))
    return q, v


def boltzmann_policy(
    mdp: TabularMDP, beta: float, gamma: float | None = None, tol: float = 1e-12
) -> torch.Tensor:
    """``[S, A]`` soft-optimal policy for ``beta * mdp.r``: ``pi(a|s) ∝ exp Q_soft(s, a)``.

    The soft Bellman backup is a ``gamma``-contraction: iterated until ``V`` moves by less
    than ``tol``. Terminal rows are uniform (their actions are one action).
    """
    gamma = _gamma(mdp, gamma)
    if not beta > 0:
        raise ValueError(f"beta (the demonstrator's inverse temperature) must be > 0, got {beta}")
    reward = beta * mdp.r * (~mdp.terminal)[:, None]
    v = torch.zeros(mdp.num_states, dtype=torch.float64)
    for _ in range(1_000_000):
        q, v_next = soft_bellman(mdp, reward, gamma, v)
        done = bool((v_next - v).abs().max() < tol)
        v = v_next
        if done:
            break
    return torch.softmax(q, dim=-1)


def discounted_occupancy(
    mdp: TabularMDP, policy: torch.Tensor, gamma: float | None = None
) -> torch.Tensor:
    """``[S, A]`` ``rho(s, a) = (1 - gamma) sum_t gamma^t Pr(s_t = s, a_t = a)`` from
    ``mdp.initial``, exact: ``d = (1 - gamma) (I - gamma P_pi^T)^-1 d_0``. Sums to 1."""
    gamma = _gamma(mdp, gamma)
    p_pi = kernel_under(mdp, policy)
    eye = torch.eye(mdp.num_states, dtype=torch.float64)
    d = (1.0 - gamma) * torch.linalg.solve(eye - gamma * p_pi.T, mdp.initial)
    return d[:, None] * policy


def sample_episodes(
    mdp: TabularMDP, policy: torch.Tensor, episodes: int, seed: int, horizon: int | None = None
) -> torch.Tensor:
    """``[M, 5]`` int64 rows ``(episode, t, s, a, s')`` of ``episodes`` episodes of
    ``policy`` ``[S, A]``, drawn from ``torch.Generator(seed)`` alone (the global RNG is
    untouched); each ends on entering a terminal state or at ``horizon`` (the time limit)."""
    T = horizon if horizon is not None else mdp.max_steps
    if T is None or int(T) < 1 or int(episodes) < 1:
        raise ValueError(f"need episodes >= 1 and a horizon >= 1, got {episodes}, {T}")
    gen = torch.Generator().manual_seed(int(seed))
    sampler = OutcomeSampler(mdp)
    s = sampler.initial(torch.rand(episodes, generator=gen, dtype=torch.float64))
    alive = torch.ones(episodes, dtype=torch.bool)
    rows = []
    for t in range(int(T)):
        a = torch.multinomial(policy[s], 1, generator=gen).view(-1)
        s_next, _, done = sampler.step(
            s, a, torch.rand(episodes, generator=gen, dtype=torch.float64)
        )
        i = alive.nonzero().view(-1)
        rows.append(torch.stack([i, torch.full_like(i, t), s[i], a[i], s_next[i]], dim=1))
        alive &= ~done
        if not alive.any():
            break
        s = torch.where(alive, s_next, s)
    return torch.cat(rows)


def empirical_occupancy(
    mdp: TabularMDP, transitions: torch.Tensor, gamma: float | None = None
) -> torch.Tensor:
    """``[S, A]`` discounted occupancy of demonstrated ``(episode, t, s, a, s')`` rows.

    Each episode weighs ``1 / N``; the step at ``t`` adds ``(1 - gamma) gamma^t`` to its
    pair, and entering a terminal state at ``t`` adds the absorbing tail ``gamma^(t+1)``
    to that state (spread over its actions, which are one). An episode cut by the time
    limit loses its tail; the total is renormalised to 1.
    """
    gamma = _gamma(mdp, gamma)
    rows = torch.as_tensor(transitions)
    S, A = mdp.num_states, mdp.num_actions
    if rows.ndim != 2 or rows.shape[1] != 5 or rows.dtype.is_floating_point or len(rows) == 0:
        raise ValueError(
            "demonstrated transitions must be a non-empty integer [M, 5] tensor of "
            f"(episode, t, s, a, s'), got {rows.dtype} {tuple(rows.shape)}"
        )
    _, t, s, a, s2 = rows.long().unbind(dim=1)
    for name, x, hi in (("state", s, S), ("next state", s2, S), ("action", a, A)):
        if ((x < 0) | (x >= hi)).any():
            raise ValueError(f"demonstrated {name}s must lie in [0, {hi}), got {x.tolist()[:8]}")
    if (t < 0).any() or mdp.terminal[s].any():
        raise ValueError("demonstrated steps need t >= 0 and a live state acted in")
    w = gamma ** t.double()
    rho = torch.zeros(S, A, dtype=torch.float64)
    rho.index_put_((s, a), (1.0 - gamma) * w, accumulate=True)
    end = mdp.terminal[s2]
    tail = (gamma * w[end])[:, None].expand(-1, A) / A
    rho.index_put_((s2[end],), tail, accumulate=True)
    return rho / rho.sum()


def shaped_reward(mdp: TabularMDP, g: torch.Tensor, h: torch.Tensor, gamma: float) -> torch.Tensor:
    """``[S, A]`` ``f(s, a) = g(s) + gamma sum_s' P(s'|s, a) h(s') - h(s)`` under ``mdp``'s kernel."""
    return g[:, None] + gamma * (mdp.P @ h) - h[:, None]


@dataclass(frozen=True, eq=False)
class AIRLResult:
    """The learned reward, potential and generator, and each round's diagnostics."""

    g: torch.Tensor  # [S] reward of the state acted in (terminal states: per absorbing step)
    h: torch.Tensor  # [S] shaping potential
    policy: torch.Tensor  # [S, A] the last generator
    occupancy_gap: torch.Tensor  # [rounds] total variation between generator and expert occupancy
    loss: torch.Tensor  # [rounds] discriminator loss after each round's fit


def airl(
    mdp: TabularMDP,
    expert_occupancy: torch.Tensor,
    *,
    gamma: float | None = None,
    rounds: int = 200,
    disc_iters: int = 20,
    sweeps: int = 1,
) -> AIRLResult:
    """Alternate ``rounds`` times: ``sweeps`` soft Bellman backups of the generator on
    ``f`` (warm-started), then the discriminator fitted by up to ``disc_iters`` damped
    Newton steps (warm-started) on the exact logistic loss

        ``- sum rho_E log sigma(f - log pi) - sum rho_pi log sigma(log pi - f)``.

    ``expert_occupancy``: ``[S, A]`` from :func:`discounted_occupancy` (unlimited
    demonstrations) or :func:`empirical_occupancy`. A single soft backup per round keeps
    the game stable (a full best response each round oscillates on FrozenLake).
    Deterministic: no randomness anywhere.
    """
    gamma = _gamma(mdp, gamma)
    S, A = mdp.num_states, mdp.num_actions
    rho_e = torch.as_tensor(expert_occupancy, dtype=torch.float64)
    if rho_e.shape != (S, A) or not torch.isfinite(rho_e).all() or (rho_e < 0).any():
        raise ValueError(f"expert occupancy must be a finite non-negative [{S}, {A}] tensor")
    if not rho_e.sum() > 0:
        raise ValueError("expert occupancy is zero everywhere: no demonstrated step")
    if int(rounds) != rounds or rounds < 1 or disc_iters < 1 or sweeps < 1:
        raise ValueError(
            f"need rounds, disc_iters, sweeps >= 1; got {rounds}, {disc_iters}, {sweeps}"
        )
    rho_e = rho_e / rho_e.sum()
    M = _shaping_matrix(mdp, gamma)  # f = M @ [g; h], flattened over (s, a)
    theta = torch.zeros(2 * S, dtype=torch.float64)
    v = torch.zeros(S, dtype=torch.float64)
    gaps, losses = torch.empty(int(rounds), dtype=torch.float64), torch.empty(int(rounds))
    for k in range(int(rounds)):
        q, v = soft_bellman(mdp, (M @ theta).view(S, A), gamma, v, sweeps)
        policy = torch.softmax(q, dim=-1)
        rho = discounted_occupancy(mdp, policy, gamma)
        log_pi = torch.log(policy).masked_fill(mdp.terminal[:, None], 0.0)
        theta, losses[k] = _fit_discriminator(
            M, theta, log_pi.reshape(-1), rho_e.reshape(-1), rho.reshape(-1), disc_iters
        )
        gaps[k] = 0.5 * float((rho - rho_e).abs().sum())
    return AIRLResult(
        g=theta[:S].clone(), h=theta[S:].clone(), policy=policy, occupancy_gap=gaps, loss=losses
    )


def _shaping_matrix(mdp: TabularMDP, gamma: float) -> torch.Tensor:
    """``[S * A, 2 S]`` ``M`` with ``(M @ [g; h])[s * A + a] = f(s, a)`` (:func:`shaped_reward`)."""
    S, A = mdp.num_states, mdp.num_actions
    eye = torch.eye(S, dtype=torch.float64).repeat_interleave(A, dim=0)  # [S * A, S]: 1{s}
    return torch.cat([eye, gamma * mdp.P.reshape(S * A, S) - eye], dim=1)


def _fit_discriminator(
    M: torch.Tensor,
    theta: torch.Tensor,
    log_pi: torch.Tensor,
    rho_e: torch.Tensor,
    rho: torch.Tensor,
    iters: int,
) -> tuple[torch.Tensor, float]:
    """Damped Newton on the convex logistic loss in ``theta`` (``x = M theta - log pi``):
    gradient ``M^T ((rho_e + rho) sigma(x) - rho_e)``, Hessian ``M^T diag((rho_e + rho)
    sigma(x) (1 - sigma(x))) M``, a backtracking line search. The constant shift
    (``g += (1 - gamma) c``, ``h += c``) leaves ``f`` unchanged: the tiny damping keeps the
    solve defined and the step off that direction."""
    weight = rho_e + rho

    def loss_at(th: torch.Tensor) -> torch.Tensor:
        x = M @ th - log_pi
        return -(rho_e * F.logsigmoid(x)).sum() - (rho * F.logsigmoid(-x)).sum()

    loss = loss_at(theta)
    for _ in range(iters):
        sig = torch.sigmoid(M @ theta - log_pi)
        grad = M.T @ (weight * sig - rho_e)
        if float(grad.abs().max()) < 1e-13:
            break
        hess = M.T @ ((weight * sig * (1 - sig))[:, None] * M)
        damping = 1e-10 * float(hess.diagonal().max()) + 1e-300
        step = torch.linalg.solve(hess + damping * torch.eye(len(theta), dtype=hess.dtype), grad)
        t = 1.0
        for _ in range(60):  # Armijo backtracking
            trial = theta - t * step
            new = loss_at(trial)
            if new <= loss - 1e-4 * t * float(grad @ step):
                break
            t *= 0.5
        else:
            break  # no decrease along the Newton direction: at the optimum to rounding
        theta, loss = trial, new
    return theta, float(loss)


def plan(
    mdp: TabularMDP, reward: torch.Tensor, gamma: float | None = None, tol: float = 1e-12
) -> torch.Tensor:
    """``[S]`` greedy table of hard value iteration on ``reward`` ``[S]`` (per step in the
    state acted in, terminal states absorbing and paying it every step) or ``[S, A]``."""
    gamma = _gamma(mdp, gamma)
    r = torch.as_tensor(reward, dtype=torch.float64)
    if r.ndim == 1:
        r = r[:, None].expand(-1, mdp.num_actions)
    if r.shape != (mdp.num_states, mdp.num_actions) or not torch.isfinite(r).all():
        raise ValueError(
            f"a reward to plan against must be finite [S] or [S, A], got {tuple(r.shape)}"
        )
    v = torch.zeros(mdp.num_states, dtype=torch.float64)
    for _ in range(1_000_000):
        q = r + gamma * (mdp.P @ v)
        v_next = q.max(dim=-1).values
        done = bool((v_next - v).abs().max() < tol)
        v = v_next
        if done:
            break
    return q.argmax(dim=-1)

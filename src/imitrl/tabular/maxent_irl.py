"""Exact tabular maximum-causal-entropy IRL (Ziebart et al. 2008, 2010) on a :class:`TabularMDP`.

Finite horizon ``T`` (the MDP's time limit), reward linear in features
``r_theta[s, a] = sum_k theta[k] phi[k, s, a]``. Terminal states take no action: their
value is 0, their reward never counts, and no occupancy accrues there.

* Soft value iteration, backwards in time (Ziebart 2010, thesis eq. 6.5; Gleave and
  Toyer 2022, "A Primer on MCE IRL", eq. 11):
  ``Q_t(s, a) = r_theta(s, a) + sum_s' P(s'|s, a) V_{t+1}(s')``, ``V_T = 0``,
  ``V_t(s) = log sum_a exp Q_t(s, a)``, ``pi_t(a|s) = exp(Q_t(s, a) - V_t(s))``.
* Occupancy forward from ``d_0``: ``D[t, s, a] = d_t(s) pi_t(a|s)`` on live states,
  ``d_{t+1}(s') = sum_{s, a} d_t(s) pi_t(a|s) P(s'|s, a)`` (terminal states absorb).
* Demonstrations enter as counts ``C[t, s, a]`` over ``N`` episodes. Two objectives:
  ``"likelihood"``: ``L = (1/N) sum_{t,s,a} C[t,s,a] log pi_t(a|s)``, the exact causal
  log-likelihood of the demonstrated actions, with its exact gradient by an adjoint pass
  (:func:`likelihood_gradient`); ``"dual"``: the MCE dual
  ``g = theta . mu_E - (1/N) sum_s C_0(s) V_0(s)`` (Gleave and Toyer eq. 19), whose
  gradient is the feature gap ``mu_E - mu_pi`` (Ziebart 2008 eq. 6). They agree when
  ``C`` is an exact occupancy; on sampled episodes they differ by the transition noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from imitrl import keys
from imitrl.tabular.finite_horizon import _horizon
from imitrl.tabular.mdp import TabularMDP

__all__ = [
    "Demonstrations",
    "IRLResult",
    "SoftPolicy",
    "dual_objective",
    "feature_expectations",
    "likelihood_gradient",
    "linear_reward",
    "log_likelihood",
    "maxent_irl",
    "next_state_features",
    "occupancy_measure",
    "soft_value_iteration",
    "state_action_features",
    "state_features",
    "time_indexed_state_distributions",
]

OBJECTIVES = ("likelihood", "dual")
OPTIMIZERS = ("adam", "sgd")


# ----------------------------------------------------------------------------- features
def state_features(num_states: int, num_actions: int) -> torch.Tensor:
    """``[S, S, A]`` one-hot of the state acted in: ``phi[k, s, a] = 1{k == s}``."""
    eye = torch.eye(num_states, dtype=torch.float64)  # [S, S]
    return eye[:, :, None].expand(num_states, num_states, num_actions).clone()


def state_action_features(num_states: int, num_actions: int) -> torch.Tensor:
    """``[S * A, S, A]`` one-hot of the pair: ``phi[s * A + a, s, a] = 1``."""
    eye = torch.eye(num_states * num_actions, dtype=torch.float64)
    return eye.view(num_states * num_actions, num_states, num_actions)


def next_state_features(mdp: TabularMDP) -> torch.Tensor:
    """``[S, S, A]`` expected one-hot of the state entered: ``phi[k, s, a] = P(k|s, a)``.

    A reward on the state entered, ``R(s, a, s') = theta[s']``, in expectation; it prices
    entering a terminal state (a goal, a hole), which a reward on the state acted in
    never can, since terminal states take no action.
    """
    return mdp.P.permute(2, 0, 1).clone()


def linear_reward(theta: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """``r_theta[s, a] = sum_k theta[k] phi[k, s, a]``: ``[K]``, ``[K, S, A]`` -> ``[S, A]``
    (``theta`` ``[B, K]`` -> ``[B, S, A]``)."""
    phi = _check_tensor(phi, "features", (-1, -1, -1))
    theta = _check_batched(theta, "theta", (phi.shape[0],))
    return torch.einsum("...k,ksa->...sa", theta, phi)


# ------------------------------------------------------------------------- soft planning
@dataclass(frozen=True, eq=False)
class SoftPolicy:
    """Soft value iteration's output; rows of terminal states are 0 (``policy``: uniform)."""

    q: torch.Tensor  # [T, S, A] Q_t(s, a)
    v: torch.Tensor  # [T + 1, S] V_t(s), V_T = 0
    policy: torch.Tensor  # [T, S, A] pi_t(a|s) = exp(Q_t - V_t)


def soft_value_iteration(
    mdp: TabularMDP, reward: torch.Tensor, horizon: int | None = None
) -> SoftPolicy:
    """Finite-horizon soft Bellman recursion (module docstring) for ``reward`` ``[S, A]``.

    ``horizon`` defaults to the MDP's time limit; ``T`` decisions at ``t = 0 .. T - 1``.
    A leading batch ``[B, S, A]`` plans B rewards at once (``q`` ``[B, T, S, A]``, ...).
    """
    T, S, A = _horizon(mdp, horizon), mdp.num_states, mdp.num_actions
    reward = _check_batched(reward, "reward", (S, A))
    batch = reward.shape[:-2]
    live = ~mdp.terminal  # [S]
    r = reward * live[:, None]  # terminal states collect nothing
    Pt = mdp.P.reshape(S * A, S).T  # [S, S * A]: one matmul per backup
    q = torch.zeros(*batch, T, S, A, dtype=torch.float64)
    v = torch.zeros(*batch, T + 1, S, dtype=torch.float64)
    for t in reversed(range(T)):
        q[..., t, :, :] = (r + (v[..., t + 1, :] @ Pt).view(*batch, S, A)) * live[:, None]
        v[..., t, :] = torch.logsumexp(q[..., t, :, :], dim=-1) * live  # V_t(terminal) = 0
    policy = torch.exp(q - v[..., :-1, :, None])
    policy[..., ~live, :] = 1.0 / A  # never used: no decision is taken in a terminal state
    return SoftPolicy(q=q, v=v, policy=policy)


def time_indexed_state_distributions(
    mdp: TabularMDP, policy: torch.Tensor, initial: torch.Tensor | None = None
) -> torch.Tensor:
    """``[T + 1, S]`` state distributions ``d_0 .. d_T`` under ``policy`` ``[T, S, A]``.

    ``d_{t+1}(s') = sum_{s,a} d_t(s) pi_t(a|s) P(s'|s, a)``; ``d_T[goal].sum()`` is the exact
    success probability of the time-indexed policy within ``T`` steps. A leading batch
    (``policy`` ``[B, T, S, A]``, ``initial`` ``[S]`` or ``[B, S]``) gives ``[B, T + 1, S]``.
    """
    S, A = mdp.num_states, mdp.num_actions
    policy = _check_batched(policy, "policy", (-1, S, A))
    batch, T = policy.shape[:-3], policy.shape[-3]
    d = torch.empty(*batch, T + 1, S, dtype=torch.float64)
    d0 = mdp.initial if initial is None else _check_batched(initial, "initial", (S,))
    d[..., 0, :] = d0
    P = mdp.P.reshape(S * A, S)  # [S * A, S]
    for t in range(T):
        d[..., t + 1, :] = (d[..., t, :, None] * policy[..., t, :, :]).reshape(*batch, S * A) @ P
    return d


def occupancy_measure(
    mdp: TabularMDP, policy: torch.Tensor, initial: torch.Tensor | None = None
) -> torch.Tensor:
    """``[T, S, A]`` ``D[t, s, a] = d_t(s) pi_t(a|s)`` on live states, 0 on terminal ones."""
    d = time_indexed_state_distributions(mdp, policy, initial)  # [..., T + 1, S]
    live = (~mdp.terminal).to(torch.float64)
    return (d[..., :-1, :] * live)[..., None] * policy


def feature_expectations(occupancy: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """``mu[k] = sum_{t,s,a} D[t, s, a] phi[k, s, a]``: ``[T, S, A]``, ``[K, S, A]`` -> ``[K]``
    (a leading batch ``[B, T, S, A]`` gives ``[B, K]``)."""
    return torch.einsum("...tsa,ksa->...k", occupancy, phi)


# ------------------------------------------------------------------------ demonstrations
@dataclass(frozen=True, eq=False)
class Demonstrations:
    """Demonstrated decisions as counts: ``counts[t, s, a]`` summed over ``episodes``."""

    counts: torch.Tensor  # [T, S, A] float64, zero on terminal states ([B, T, S, A]: B sets)
    episodes: float | torch.Tensor  # N: the divisor turning sums into per-episode means ([B])

    @classmethod
    def stack(cls, demos: list[Demonstrations]) -> Demonstrations:
        """B unbatched demonstration sets as one batch: fitted at once, each on its own."""
        if not demos or any(d.counts.ndim != 3 for d in demos):
            raise ValueError("stack needs a non-empty list of unbatched Demonstrations")
        if len({tuple(d.counts.shape) for d in demos}) != 1:
            raise ValueError(f"shapes differ: {sorted({tuple(d.counts.shape) for d in demos})}")
        episodes = torch.tensor([float(d.episodes) for d in demos], dtype=torch.float64)
        return cls(counts=torch.stack([d.counts for d in demos]), episodes=episodes)

    def per_episode(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``[..., *]`` divided by each set's episode count (broadcast on the batch)."""
        n = torch.as_tensor(self.episodes, dtype=torch.float64)
        return x / n.reshape(n.shape + (1,) * (x.ndim - n.ndim))

    @classmethod
    def from_tuples(cls, mdp: TabularMDP, rows: torch.Tensor, horizon: int | None = None):
        """From an integer ``[M, 4]`` tensor of ``(episode, t, s, a)`` rows."""
        rows = torch.as_tensor(rows)
        if rows.ndim != 2 or rows.shape[1] != 4 or rows.dtype.is_floating_point:
            raise ValueError(
                f"demonstration tuples must be an integer [M, 4] tensor of (episode, t, s, a), "
                f"got {rows.dtype} {tuple(rows.shape)}"
            )
        return cls._count(mdp, rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], horizon)

    @classmethod
    def from_rows(cls, mdp: TabularMDP, rows: TensorDictBase, horizon: int | None = None):
        """From buffer rows: keys ``observation``, ``expert_action``, ``step``, ``episode``."""
        missing = [
            k
            for k in (keys.EPISODE, keys.STEP, keys.OBSERVATION, keys.EXPERT_ACTION)
            if k not in rows.keys()
        ]
        if missing:
            raise ValueError(f"demonstration rows lack the keys {missing}")
        get = lambda k: rows.get(k).reshape(-1)  # noqa: E731
        return cls._count(
            mdp,
            get(keys.EPISODE),
            get(keys.STEP),
            get(keys.OBSERVATION),
            get(keys.EXPERT_ACTION),
            horizon,
        )

    @classmethod
    def from_occupancy(cls, occupancy: torch.Tensor) -> Demonstrations:
        """An exact occupancy ``[T, S, A]`` as the demonstration (one expected episode)."""
        occupancy = torch.as_tensor(occupancy, dtype=torch.float64)
        if occupancy.ndim != 3 or not torch.isfinite(occupancy).all() or (occupancy < 0).any():
            raise ValueError("an occupancy must be a finite non-negative [T, S, A] tensor")
        return cls(counts=occupancy, episodes=1.0)

    @classmethod
    def _count(cls, mdp, episode, t, s, a, horizon) -> Demonstrations:
        T, S, A = _horizon(mdp, horizon), mdp.num_states, mdp.num_actions
        for name, x, hi in (("t", t, T), ("state", s, S), ("action", a, A)):
            if x.dtype.is_floating_point or ((x < 0) | (x >= hi)).any():
                raise ValueError(
                    f"demonstrated {name} must be integers in [0, {hi}), got {x.tolist()[:8]}..."
                )
        if len(s) == 0:
            raise ValueError("no demonstrated decisions")
        if mdp.terminal[s].any():
            bad = int(s[mdp.terminal[s]][0])
            raise ValueError(
                f"demonstrated state {bad} is terminal: an episode takes no action there"
            )
        counts = torch.zeros(T, S, A, dtype=torch.float64)
        counts.index_put_(
            (t.long(), s.long(), a.long()), torch.ones(len(s), dtype=torch.float64), accumulate=True
        )
        return cls(counts=counts, episodes=float(torch.unique(episode).numel()))


# ------------------------------------------------------------------ objectives, gradients
def _log_likelihoods(soft: SoftPolicy, demos: Demonstrations) -> torch.Tensor:
    """``[]`` or ``[B]`` mean log-likelihood per episode of each demonstration set."""
    logp = soft.q - soft.v[..., :-1, :, None]  # [..., T, S, A] log pi_t(a|s), exact
    return demos.per_episode((demos.counts * logp).sum(dim=(-3, -2, -1)))


def log_likelihood(soft: SoftPolicy, demos: Demonstrations) -> float | torch.Tensor:
    """``(1/N) sum_{t,s,a} C[t, s, a] log pi_t(a|s)``: mean log-likelihood per episode
    (a float; a ``[B]`` tensor for batched demonstrations)."""
    ll = _log_likelihoods(soft, demos)
    return float(ll) if ll.ndim == 0 else ll


def likelihood_gradient(
    mdp: TabularMDP, soft: SoftPolicy, demos: Demonstrations, phi: torch.Tensor
) -> torch.Tensor:
    """``[K]`` exact gradient of :func:`log_likelihood` in ``theta`` (``[B, K]`` batched).

    ``dL = sum_t nu_t . dQ_t`` with ``nu_t = C_t - pi_t c_t`` (``c_t(s) = sum_a C_t(s, a)``);
    unrolling ``dQ_t = dr + P dV_{t+1}`` forward gives the adjoint occupancy
    ``X_t = C_t - pi_t (c_t - m_t)``, ``m_{t+1} = live * (X_t P)``, ``m_0 = 0``, and
    ``dL/dtheta = (1/N) sum_t X_t . phi``: the demonstrated features minus those of the
    soft policy re-started from every demonstrated state the kernel did not predict.
    """
    S, A = mdp.num_states, mdp.num_actions
    batch, T = demos.counts.shape[:-3], demos.counts.shape[-3]
    live = (~mdp.terminal).to(torch.float64)
    P = mdp.P.reshape(S * A, S)  # [S * A, S]
    m = torch.zeros(*batch, S, dtype=torch.float64)
    X = torch.empty_like(demos.counts)  # [..., T, S, A]
    for t in range(T):
        C_t, pi_t = demos.counts[..., t, :, :], soft.policy[..., t, :, :]
        X[..., t, :, :] = (C_t - pi_t * (C_t.sum(dim=-1) - m)[..., None]) * live[:, None]
        m = (X[..., t, :, :].reshape(*batch, S * A) @ P) * live
    return demos.per_episode(feature_expectations(X, phi))


def dual_objective(
    soft: SoftPolicy, demos: Demonstrations, theta: torch.Tensor, phi
) -> float | torch.Tensor:
    """MCE dual ``g = theta . mu_E - (1/N) sum_s C_0(s) V_0(s)``; gradient ``mu_E - mu_pi``."""
    mu_E = demos.per_episode(feature_expectations(demos.counts, phi))
    start = demos.per_episode(demos.counts[..., 0, :, :].sum(dim=-1))  # [..., S] empirical d_0
    g = (theta * mu_E).sum(-1) - (start * soft.v[..., 0, :]).sum(-1)
    return float(g) if g.ndim == 0 else g


def _feature_gap(mdp, soft: SoftPolicy, demos: Demonstrations, phi) -> torch.Tensor:
    """``[..., K]`` ``mu_E - mu_pi``, the soft policy started from the demonstrations' ``d_0``."""
    start = demos.per_episode(demos.counts[..., 0, :, :].sum(dim=-1))  # [..., S]
    mu_pi = feature_expectations(occupancy_measure(mdp, soft.policy, start), phi)
    return demos.per_episode(feature_expectations(demos.counts, phi)) - mu_pi


# ------------------------------------------------------------------------------ the fit
@dataclass(frozen=True, eq=False)
class IRLResult:
    """What :func:`maxent_irl` recovers (batched demonstrations: a leading ``[B]`` on each)."""

    theta: torch.Tensor  # [K] reward weights
    reward: torch.Tensor  # [S, A] r_theta (zero on terminal states)
    q: torch.Tensor  # [T, S, A] soft Q_t of r_theta
    policy: torch.Tensor  # [T, S, A] soft-optimal pi_t(a|s)
    log_likelihood: torch.Tensor  # [steps + 1] mean log-likelihood per episode, per iterate
    feature_gap: torch.Tensor  # [K] mu_E - mu_pi at the final theta

    def greedy(self) -> torch.Tensor:
        """``[S]`` (``[B, S]``) stationary greedy policy: argmax of the soft ``Q_0``."""
        return self.q[..., 0, :, :].argmax(dim=-1)


def maxent_irl(
    mdp: TabularMDP,
    demos: Demonstrations,
    features: torch.Tensor,
    *,
    horizon: int | None = None,
    steps: int = 500,
    lr: float = 0.1,
    l2: float = 0.0,
    objective: str = "likelihood",
    optimizer: str = "adam",
    theta0: torch.Tensor | None = None,
) -> IRLResult:
    """Fit ``theta`` by gradient ascent on ``objective - (l2 / 2) |theta|^2``.

    Args:
        demos: counts from :class:`Demonstrations` (tuples, buffer rows or an occupancy).
        features: ``[K, S, A]`` ``phi`` (:func:`state_features`, :func:`next_state_features`,
            :func:`state_action_features`, or your own).
        horizon: ``T``; defaults to the MDP's time limit; must match ``demos.counts``.
        objective: ``"likelihood"`` (exact causal log-likelihood) or ``"dual"`` (MCE dual,
            gradient = feature gap); see the module docstring.
        optimizer: ``"adam"`` (``torch.optim.Adam``) or ``"sgd"`` (plain ascent).
        theta0: ``[K]`` start; zeros by default. Deterministic: no randomness anywhere.
    """
    T, S, A = _horizon(mdp, horizon), mdp.num_states, mdp.num_actions
    phi = _check_tensor(features, "features", (-1, S, A))
    counts = _check_batched(demos.counts, "demonstration counts", (T, S, A))
    if objective not in OBJECTIVES or optimizer not in OPTIMIZERS:
        raise ValueError(f"objective must be one of {OBJECTIVES} and optimizer one of {OPTIMIZERS}")
    if int(steps) != steps or steps < 0 or not lr > 0 or not l2 >= 0:
        raise ValueError(f"need integer steps >= 0, lr > 0, l2 >= 0; got {steps}, {lr}, {l2}")
    batch, K = counts.shape[:-3], phi.shape[0]
    start = torch.zeros(*batch, K, dtype=torch.float64) if theta0 is None else theta0
    theta = _check_batched(start, "theta0", (K,)).expand(*batch, K).clone()
    # Adam and SGD update elementwise: B rows of theta are B independent fits
    opt = (torch.optim.Adam if optimizer == "adam" else torch.optim.SGD)(
        [theta], lr=lr, maximize=True
    )
    history = torch.empty(int(steps) + 1, *batch, dtype=torch.float64)
    for k in range(int(steps) + 1):
        soft = soft_value_iteration(mdp, linear_reward(theta, phi), T)
        history[k] = _log_likelihoods(soft, demos)
        if k == steps:
            break
        if objective == "likelihood":
            grad = likelihood_gradient(mdp, soft, demos, phi)
        else:
            grad = _feature_gap(mdp, soft, demos, phi)
        theta.grad = grad - l2 * theta
        opt.step()
    return IRLResult(
        theta=theta.detach().clone(),
        reward=linear_reward(theta, phi) * (~mdp.terminal)[:, None],
        q=soft.q,
        policy=soft.policy,
        log_likelihood=history.movedim(0, -1),
        feature_gap=_feature_gap(mdp, soft, demos, phi),
    )


def _check_tensor(x, name: str, shape: tuple[int, ...], batch: bool = False) -> torch.Tensor:
    """``x`` as a finite float64 tensor of ``shape`` (``-1``: any size), else ``ValueError``."""
    t = torch.as_tensor(x)
    if t.is_complex() or t.dtype == torch.bool:
        raise ValueError(f"{name} must be real, got dtype {t.dtype}")
    t = t.to(torch.float64)
    if t.ndim != len(shape) or any(w != -1 and w != n for w, n in zip(shape, t.shape)):
        dims = ["B" if batch and i == 0 else "K" if w == -1 and i == int(batch) else
                "*" if w == -1 else str(w) for i, w in enumerate(shape)]  # fmt: skip
        raise ValueError(f"{name} must have shape [{', '.join(dims)}], got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite, found {int((~torch.isfinite(t)).sum())} NaN/inf")
    return t


def _check_batched(x, name: str, shape: tuple[int, ...]) -> torch.Tensor:
    """:func:`_check_tensor` allowing one leading batch dimension: ``[B, *shape]``."""
    t = torch.as_tensor(x)
    if t.ndim == len(shape) + 1:
        return _check_tensor(t, name, (-1, *shape), batch=True)
    return _check_tensor(t, name, shape)

"""The study's figures, drawn with matplotlib's object API (no pyplot global state)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from imitrl.plotting import save_figure

__all__ = [
    "grid_shape",
    "plot_budget",
    "plot_chain",
    "plot_corruption",
    "plot_dagger",
    "plot_demo_counts",
    "plot_occupancy",
    "plot_state_errors",
    "plot_sweep",
]

# FrozenLake's action encoding: 0 LEFT, 1 DOWN, 2 RIGHT, 3 UP as (dx, dy) in image coordinates
_ARROWS = {0: (-1.0, 0.0), 1: (0.0, 1.0), 2: (1.0, 0.0), 3: (0.0, -1.0)}


def _save(fig: Figure, path: Path) -> Path:
    """:func:`imitrl.plotting.save_figure`: constrained layout, every label on the canvas."""
    return save_figure(fig, path, dpi=110)


def grid_shape(env_id: str, make_kwargs: dict, num_states: int) -> tuple[int, int] | None:
    """``(rows, cols)`` of a grid world without a letter map whose states are its cells in
    row-major order (CliffWalking's ``unwrapped.shape``, 4 x 12); None for any other env."""
    from imitrl.tabular.gym_model import make_env

    env = make_env(env_id, make_kwargs)
    try:
        shape = getattr(env.unwrapped, "shape", None)
    finally:
        env.close()
    if shape is None or len(shape) != 2 or int(np.prod(shape)) != num_states:
        return None
    return int(shape[0]), int(shape[1])


def _nothing(path: Path, title: str, why: str) -> Path:
    """A figure that says why there is nothing to draw (an empty sweep, no chain panels)."""
    fig = Figure(figsize=(5.5, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    ax.text(0.5, 0.5, why, ha="center", va="center", transform=ax.transAxes)
    ax.set_axis_off()
    ax.set_title(title)
    return _save(fig, path)


def plot_chain(panels: Sequence[dict], path: Path) -> Path:
    """Log-log lost return vs horizon, one panel per (eps, T): measured, exact and references."""
    if not panels:
        return _nothing(path, "compounding error on the chain", "no panels (--chain-panels)")
    fig = Figure(figsize=(5.2 * len(panels), 4.0))
    for i, p in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        T = np.arange(1, len(p["cloned"]) + 1)
        eps = p["eps"]
        ax.plot(T, p["cloned"], "o", ms=4, color="C0", label="cloned (simulated)")
        ax.plot(T, p["cloned_exact"], "-", color="C0", alpha=0.6, label="cloned (exact)")
        ax.plot(T, eps * T**2 / 2, "--", color="C0", label=r"$\varepsilon T^2/2$")
        ax.plot(T, p["recovering"], "s", ms=4, color="C1", label="recovering (simulated)")
        ax.plot(T, eps * T, "--", color="C1", label=r"$\varepsilon T$")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("horizon T")
        ax.set_ylabel("return lost to the expert")
        ax.set_title(f"({'ab'[i] if i < 2 else i}) $\\varepsilon$ = {eps}")
        ax.legend(fontsize=8)
    return _save(fig, path)


def _grid(ax, desc: np.ndarray, values: np.ndarray, policy: np.ndarray, title: str, vmax: float):
    rows, cols = desc.shape
    im = ax.imshow(values.reshape(rows, cols), cmap="Blues", vmin=0.0, vmax=vmax)
    for r in range(rows):
        for c in range(cols):
            s = r * cols + c
            letter = desc[r, c].decode() if isinstance(desc[r, c], bytes) else str(desc[r, c])
            ax.text(
                c - 0.38, r - 0.3, letter, fontsize=8, color="crimson" if letter == "H" else "black"
            )
            ax.text(c + 0.38, r + 0.38, f"{values[s]:.2f}", fontsize=6, ha="right", va="bottom")
            if letter in ("F", "S") and int(policy[s]) in _ARROWS:
                dx, dy = _ARROWS[int(policy[s])]
                ax.arrow(
                    c - 0.25 * dx,
                    r - 0.25 * dy,
                    0.3 * dx,
                    0.3 * dy,
                    head_width=0.15,
                    color="darkorange",
                )
    ax.set_xticks(range(cols))
    ax.set_yticks(range(rows))
    ax.set_title(title)
    return im


def _occupancy_curves(occupancies, titles, path: Path) -> Path:
    """Occupancy against the state index, the first policy (the expert) drawn on top."""
    fig = Figure(figsize=(7.0, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    states = np.arange(len(occupancies[0]))
    styles = [{"ls": "-", "lw": 2.5, "alpha": 0.6}, {"ls": "--", "marker": ".", "ms": 4}]
    for i, (occ, title) in reversed(list(enumerate(zip(occupancies, titles)))):
        style = styles[min(i, 1)] if i < 2 else {"ls": ":"}
        # the expert last and above: where the curves coincide, both stay visible
        ax.step(states, occ, where="mid", color=f"C{i}", label=title, zorder=3 - min(i, 2),
                **style)  # fmt: skip
    ax.set_xlabel("state")
    ax.set_ylabel("average state occupancy")
    ax.set_title("state occupancy (no grid map for this env)")
    handles, labels = ax.get_legend_handles_labels()
    ax.legend(handles[::-1], labels[::-1], fontsize=8, loc="upper center",
              bbox_to_anchor=(0.5, -0.15), ncol=len(labels))  # fmt: skip
    return _save(fig, path)


def plot_occupancy(
    desc: np.ndarray | None,
    occupancies: Sequence[np.ndarray],
    policies: Sequence[np.ndarray],
    titles: Sequence[str],
    path: Path,
    *,
    shape: tuple[int, int] | None = None,
) -> Path:
    """Occupancy maps side by side, with each policy's greedy arrows on the frozen cells.

    Without a letter map (``desc`` None) but with a grid ``shape`` (CliffWalking's 4 x 12,
    :func:`grid_shape`), the maps are drawn on that grid without letters or arrows (the
    arrows follow FrozenLake's action encoding). Without either (Taxi, raw arrays) the
    occupancies are drawn against the state index, one curve per policy.
    """
    if desc is None and shape is None:
        return _occupancy_curves(occupancies, titles, path)
    grid_shape = desc.shape if desc is not None else shape
    assert grid_shape is not None  # returned above without either
    rows, cols = grid_shape
    n = len(occupancies)
    wide = cols > 1.5 * rows  # CliffWalking's 4 x 12: the maps one above the other
    grid = (n, 1) if wide else (1, n)
    size = (0.6 * cols + 1.8, (0.6 * rows + 0.9) * n) if wide else (4.2 * n + 0.8, 4.0)
    fig = Figure(figsize=size)
    vmax = float(max(o.max() for o in occupancies))
    im = None
    for i, (occ, pol, title) in enumerate(zip(occupancies, policies, titles)):
        ax = fig.add_subplot(*grid, i + 1)
        if desc is not None:
            im = _grid(ax, desc, occ, pol, title, vmax)
        else:
            im = _plain_grid(ax, (rows, cols), occ, title, vmax)
    assert im is not None  # one map at least (max() above refuses none)
    fig.colorbar(im, ax=fig.axes, label="average state occupancy", shrink=0.8)
    return save_figure(fig, path, dpi=120)


def _plain_grid(ax, shape: tuple[int, int], values: np.ndarray, title: str, vmax: float):
    """``values`` on a ``rows x cols`` grid (row-major states), no letters, no arrows."""
    rows, cols = shape
    im = ax.imshow(values.reshape(rows, cols), cmap="Blues", vmin=0.0, vmax=vmax)
    for s in np.flatnonzero(values > 0.005):
        r, c = divmod(int(s), cols)
        ax.text(c, r, f"{values[s]:.2f}", fontsize=5, ha="center", va="center")
    ax.set_xticks(range(cols))
    ax.set_yticks(range(rows))
    ax.tick_params(labelsize=7)
    ax.set_title(f"{title} ({rows} x {cols} grid)")
    return im


def plot_sweep(
    sizes: Sequence[int],
    rates: Sequence[np.ndarray],
    exact: Sequence[np.ndarray],
    expert: float,
    path: Path,
) -> Path:
    """Success of each cloned dataset by dataset size: Monte Carlo and exact."""
    if not sizes:
        return _nothing(path, "cloning from redrawn datasets", "no dataset sizes (--sweep-sizes)")
    fig = Figure(figsize=(5.5, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    for i, (r, e) in enumerate(zip(rates, exact)):
        x = np.full(len(r), i) + np.linspace(-0.15, 0.15, len(r))
        ax.plot(x, r, "o", color="C0", label="measured" if i == 0 else None)
        ax.plot(x, e, "x", color="C3", label="exact" if i == 0 else None)
    ax.axhline(expert, ls="--", color="gray", label="expert (exact)")
    ax.set_xticks(range(len(sizes)), [f"{n} episode{'s' if n > 1 else ''}" for n in sizes])
    ax.set_ylabel("success rate of the clone")
    ax.set_title("cloning from redrawn datasets")
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_dagger(
    pairs: Sequence[int],
    rates: Sequence[float],
    ci: Sequence[tuple[float, float]],
    exact: Sequence[float],
    expert: float,
    path: Path,
) -> Path:
    """Success per DAgger round (measured with interval, exact) and the pairs trained on."""
    fig = Figure(figsize=(5.5, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    k = np.arange(len(rates))
    # at 0% or 100% the Wilson bound sits a rounding error past the rate: bars are >= 0
    lo = np.maximum(0.0, [r - c[0] for r, c in zip(rates, ci)])
    hi = np.maximum(0.0, [c[1] - r for r, c in zip(rates, ci)])
    ax.errorbar(k, rates, yerr=[lo, hi], fmt="o-", capsize=3, label="measured (95% CI)")
    ax.plot(k, exact, "x--", color="C3", label="exact")
    ax.axhline(expert, ls=":", color="gray", label="expert (exact)")
    ax.set_xlabel("DAgger round")
    ax.set_ylabel("success rate")
    ax.set_xticks(k, [f"{i}\n({p} pairs)" for i, p in zip(k, pairs)])
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_demo_counts(
    counts: Sequence[int], success: np.ndarray, accuracy: np.ndarray, expert: float, path: Path
) -> Path:
    """Exercise: exact success and expert-state accuracy against the number of demonstrations."""
    if not len(counts):
        return _nothing(path, "how many demonstrations", "no counts (--ex-demo-counts)")
    fig = Figure(figsize=(10, 4.0))
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    for ax, y, label in (
        (ax1, success, "exact success of the clone"),
        (ax2, accuracy, "agreement with the expert on the expert's states"),
    ):
        for i, n in enumerate(counts):
            ax.plot(np.full(y.shape[1], n), y[i], "o", alpha=0.4, color="C0")
        ax.plot(counts, y.mean(axis=1), "-", color="C0", label="mean over datasets")
        ax.set_xscale("log")
        ax.set_xlabel("demonstration episodes N")
        ax.set_ylabel(label)
    ax1.axhline(expert, ls="--", color="gray", label="expert")
    ax2.axhline(1.0, ls="--", color="gray")
    ax1.legend(fontsize=8)
    return _save(fig, path)


def plot_state_errors(
    visitation: np.ndarray, error: np.ndarray, states: Sequence[int], path: Path
) -> Path:
    """Exercise: per-state disagreement with the expert vs the expert's visitation frequency."""
    fig = Figure(figsize=(5.5, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    x = np.maximum(visitation, 1e-4)
    ax.plot(x, error, "o")
    for xi, yi, s in zip(x, error, states):
        ax.annotate(str(s), (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("expert's visitation frequency (exact; 1e-4 = never)")
    ax.set_ylabel("P(clone's greedy action != expert's)")
    ax.set_title("where the clone's errors are")
    return _save(fig, path)


def plot_budget(
    budget: np.ndarray,
    dagger: np.ndarray,
    bc: np.ndarray,
    bc_demo: np.ndarray,
    expert: float,
    path: Path,
) -> Path:
    """Exercise: DAgger vs BC given the same number of expert labels (one point per seed)."""
    fig = Figure(figsize=(5.5, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(budget, dagger, "o", label="DAgger (final round)")
    ax.plot(budget, bc, "s", label="BC, same number of expert labels")
    ax.plot(budget, bc_demo, "^", alpha=0.6, label="BC on DAgger's initial demonstrations")
    ax.axhline(expert, ls="--", color="gray", label="expert")
    ax.set_xlabel("expert labels used")
    ax.set_ylabel("exact success")
    # below the axes: points sit at the expert's line and anywhere under it
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.17), ncol=2)
    return _save(fig, path)


def plot_corruption(
    labels: Sequence[str], clean: np.ndarray, corrupted: np.ndarray, path: Path
) -> Path:
    """Exercise: exact success with clean vs corrupted expert labels (mean and per-seed points)."""
    fig = Figure(figsize=(5.5, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(labels))
    ax.bar(x - 0.2, clean.mean(axis=1), width=0.4, label="clean labels", alpha=0.7)
    ax.bar(x + 0.2, corrupted.mean(axis=1), width=0.4, label="corrupted labels", alpha=0.7)
    for i in range(len(labels)):
        ax.plot(np.full(clean.shape[1], i - 0.2), clean[i], "k.", alpha=0.5)
        ax.plot(np.full(corrupted.shape[1], i + 0.2), corrupted[i], "k.", alpha=0.5)
    ax.set_xticks(x, labels)
    ax.set_ylabel("exact success")
    ax.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2)  # not on a bar
    return _save(fig, path)

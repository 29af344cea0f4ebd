"""Section 8's figures: the recovered reward on the map, and IRL vs BC vs DAgger by dataset size."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from imitrl.experiments.frozenlake.figures import _ARROWS, _nothing, _save

__all__ = ["plot_airl_transfer", "plot_irl_sweep", "plot_reward"]

_METHODS = {"irl": ("MaxEnt IRL", "C2"), "bc": ("BC", "C3"), "dagger": ("DAgger", "C0")}


def plot_reward(desc: np.ndarray | None, theta: np.ndarray, policy: np.ndarray, path: Path) -> Path:
    """``theta[s']``, the reward for entering each state, on the map with the greedy arrows.

    Without a grid map (``desc`` None) the reward is drawn against the state index.
    """
    fig = Figure(figsize=(5.2, 4.4))
    ax = fig.add_subplot(1, 1, 1)
    lim = float(np.abs(theta).max()) or 1.0
    if desc is None:
        ax.bar(np.arange(len(theta)), theta, color=np.where(theta >= 0, "C2", "C3"))
        ax.set_xlabel("state entered")
        ax.set_ylabel("recovered reward")
        ax.set_title("MaxEnt IRL: reward for entering each state")
        return _save(fig, path)
    rows, cols = desc.shape
    im = ax.imshow(theta.reshape(rows, cols), cmap="RdBu", vmin=-lim, vmax=lim)
    for r in range(rows):
        for c in range(cols):
            s = r * cols + c
            letter = desc[r, c].decode() if isinstance(desc[r, c], bytes) else str(desc[r, c])
            ax.text(c - 0.38, r - 0.3, letter, fontsize=9, fontweight="bold")
            ax.text(c + 0.4, r + 0.4, f"{theta[s]:+.2f}", fontsize=7, ha="right", va="bottom")
            if letter in ("F", "S") and int(policy[s]) in _ARROWS:
                dx, dy = _ARROWS[int(policy[s])]
                ax.arrow(c - 0.2 * dx, r - 0.2 * dy, 0.3 * dx, 0.3 * dy, head_width=0.15)
    ax.set_xticks(range(cols))
    ax.set_yticks(range(rows))
    ax.set_title("reward for entering each cell\narrows: greedy plan")
    fig.colorbar(im, ax=ax, shrink=0.85, label="recovered reward theta[s']")
    return _save(fig, path)


def plot_irl_sweep(
    scores: Mapping[int, Mapping[str, np.ndarray]], expert: float, path: Path
) -> Path:
    """Exact success of every dataset's IRL, BC and DAgger policy, by dataset size."""
    if not scores:
        return _nothing(path, "IRL vs BC vs DAgger", "no dataset sizes (--irl-sizes)")
    fig = Figure(figsize=(6.2, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    sizes = list(scores)
    for j, (key, (label, color)) in enumerate(_METHODS.items()):
        for i, n in enumerate(sizes):
            v = np.asarray(scores[n][key])
            x = i + (j - 1) * 0.25 + np.linspace(-0.07, 0.07, len(v))
            ax.plot(x, v, "o", ms=4, color=color, alpha=0.8, label=label if i == 0 else None)
            ax.plot([i + (j - 1) * 0.25 - 0.1, i + (j - 1) * 0.25 + 0.1], [np.median(v)] * 2,
                    color=color, lw=2)  # fmt: skip
    ax.axhline(expert, ls="--", color="gray", label="expert")
    ax.set_xticks(range(len(sizes)), [f"{n} episode{'s' if n > 1 else ''}" for n in sizes])
    ax.set_ylabel("exact success probability")
    ax.set_ylim(-0.02, 1.0)
    ax.set_title("redrawn datasets: each dot one dataset, bar the median")
    ax.legend(fontsize=8, loc="lower right")
    return _save(fig, path)


_TRANSFER = {
    "airl_g": ("AIRL g(s)", "C0", "o-"),
    "airl_f": ("AIRL f(s, a), source shaping", "C1", "s--"),
    "maxent": ("MaxEnt IRL theta[s']", "C2", "^-"),
    "source_expert": ("source expert's policy", "gray", ":"),
}


def plot_airl_transfer(rows: list[dict], methods: tuple[str, ...], path: Path) -> Path:
    """One panel per kernel: each method's normalised return against the dataset."""
    targets = list(dict.fromkeys(r["target"] for r in rows))
    if not targets:
        return _nothing(path, "AIRL transfer", "no fits")
    datasets = list(dict.fromkeys(r["dataset"] for r in rows))
    n = len(targets)
    fig = Figure(figsize=(3.2 * n + 2.6, 3.8))
    axes = fig.subplots(1, n + 1, gridspec_kw={"width_ratios": [1] * n + [0.8]})
    for ax, target in zip(axes[:n], targets):
        by = {r["dataset"]: r for r in rows if r["target"] == target}
        for m in methods:
            label, color, style = _TRANSFER[m]
            y = [by[d][m]["normalised_return"] for d in datasets]
            y = [np.nan if v is None else v for v in y]  # undefined: no policy beats chance
            ax.plot(range(len(datasets)), y, style, color=color, label=label, ms=4)
        ax.axhline(1.0, color="black", lw=0.6)
        ax.set_xticks(range(len(datasets)), [d.replace(" episodes", "") for d in datasets])
        ax.set_xlabel("demonstrated episodes")
        ax.set_ylim(-0.1, 1.1)
        ax.set_title(target if target != "source" else "source (training) kernel", fontsize=9)
    axes[0].set_ylabel("normalised return\n(own optimum 1, uniform 0)")
    axes[n].axis("off")  # the legend's own panel: no line hidden under it
    axes[n].legend(*axes[0].get_legend_handles_labels(), loc="center left", fontsize=8)
    fig.suptitle("rewards planned against under each kernel, exact", fontsize=10)
    return _save(fig, path)

"""LeRobot's per-feature statistics, computed as lerobot 0.4's ``compute_stats`` does.

``meta/stats.json`` and each episode's ``stats/<feature>/<stat>`` columns hold
``min, max, mean, std, count`` and the :data:`QUANTILES` (``q01 ... q99``); LeRobot
checks their shapes when datasets are merged or resumed, so they are reduced over the
same axes it reduces them over.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imitrl.datasets.lerobot._layout import QUANTILES


def _summary(x: np.ndarray, xf: np.ndarray, shape: tuple[int, ...], count: int) -> dict[str, Any]:
    """min/max of ``x [M, C]``, mean/std/quantiles of ``xf`` (``x`` as float64, maybe
    scaled) over its ``M`` rows, each reshaped to ``shape``; ``count`` as given."""
    out: dict[str, Any] = {
        "min": x.min(axis=0).reshape(shape),
        "max": x.max(axis=0).reshape(shape),
        "mean": xf.mean(axis=0).reshape(shape),
        "std": xf.std(axis=0).reshape(shape),
        "count": np.array([count]),
    }
    for q in QUANTILES:
        out[f"q{round(q * 100):02d}"] = np.quantile(xf, q, axis=0).reshape(shape)
    return out


def feature_stats(values: np.ndarray) -> dict[str, Any]:
    """LeRobot's per-feature statistics (lerobot 0.4 ``compute_stats.get_feature_stats``):
    scalars and vectors over frames; arrays of 2+ dims over every axis but the last, as
    its ``RunningQuantileStats`` reduces them (resuming or merging datasets needs the
    same shapes)."""
    x = values[:, None] if values.ndim == 1 else values.reshape(-1, values.shape[-1])
    return _summary(x, x.astype(np.float64), (x.shape[-1],), values.shape[0])


def sample_frames(chw: np.ndarray) -> np.ndarray:
    """The frames LeRobot's image statistics read (lerobot 0.4 ``compute_stats.sample_images``):
    ``estimate_num_samples`` of them evenly spaced, each downsampled as
    ``auto_downsample_height_width`` does."""
    n = len(chw)
    k = n if n < 100 else max(100, min(int(n**0.75), 10_000))
    frames = chw[np.round(np.linspace(0, n - 1, k)).astype(int)]
    height, width = frames.shape[2:]
    if max(width, height) >= 300:
        factor = int(width / 150) if width > height else int(height / 150)
        frames = frames[:, :, ::factor, ::factor]
    return frames


def image_stats(frames: np.ndarray) -> dict[str, Any]:
    """LeRobot's image statistics (``compute_episode_stats``): per channel over the pixels of
    the sampled ``[k, C, H, W]`` frames, scaled to [0, 1], shaped ``(C, 1, 1)``; ``count``
    is the number of frames sampled."""
    channels = frames.shape[1]
    x = frames.transpose(0, 2, 3, 1).reshape(-1, channels).astype(np.float64) / 255.0
    return _summary(x, x, (channels, 1, 1), len(frames))


def aggregate_stats(per_episode: list[dict[str, Any]]) -> dict[str, Any]:
    """One feature's statistics over the whole dataset from its episodes' (lerobot 0.4
    ``compute_stats.aggregate_feature_stats``): min of mins, max of maxes, the count-weighted
    mean, the pooled variance ``sum_e c_e (var_e + (mean_e - mean)^2) / sum_e c_e``, summed
    counts, and each quantile as the count-weighted mean of the episodes' quantiles."""
    means = np.stack([s["mean"] for s in per_episode])  # [E, *shape]
    variances = np.stack([s["std"] ** 2 for s in per_episode])
    counts = np.stack([s["count"] for s in per_episode])  # [E, 1]
    total = counts.sum(axis=0)  # [1]
    weights = counts.reshape(len(counts), *([1] * (means.ndim - 1)))  # [E, 1, ...]
    mean = (means * weights).sum(axis=0) / total
    variance = ((variances + (means - mean) ** 2) * weights).sum(axis=0) / total
    out: dict[str, Any] = {
        "min": np.min(np.stack([s["min"] for s in per_episode]), axis=0),
        "max": np.max(np.stack([s["max"] for s in per_episode]), axis=0),
        "mean": mean,
        "std": np.sqrt(variance),
        "count": total,
    }
    for q in QUANTILES:
        name = f"q{round(q * 100):02d}"
        out[name] = (np.stack([s[name] for s in per_episode]) * weights).sum(axis=0) / total
    return out

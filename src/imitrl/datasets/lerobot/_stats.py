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
    ``compute_stats.aggregate_feature_stats``): :func:`aggregate_arrays` of them stacked."""
    return aggregate_arrays({k: np.stack([s[k] for s in per_episode]) for k in per_episode[0]})


def aggregate_arrays(stacked: dict[str, np.ndarray]) -> dict[str, Any]:
    """One feature's statistics over the whole dataset from its ``E`` episodes' stacked
    ``stat -> [E, *shape]`` (``count``: ``[E, 1]``), as lerobot 0.4's
    ``compute_stats.aggregate_feature_stats``: min of mins, max of maxes, the count-weighted
    mean, the pooled variance ``sum_e c_e (var_e + (mean_e - mean)^2) / sum_e c_e``, summed
    counts, and each quantile as the count-weighted mean of the episodes' quantiles."""
    means = stacked["mean"]  # [E, *shape]
    variances = stacked["std"] ** 2
    counts = stacked["count"]  # [E, 1]
    total = counts.sum(axis=0)  # [1]
    weights = counts.reshape(len(counts), *([1] * (means.ndim - 1)))  # [E, 1, ...]
    mean = (means * weights).sum(axis=0) / total
    variance = ((variances + (means - mean) ** 2) * weights).sum(axis=0) / total
    out: dict[str, Any] = {
        "min": np.min(stacked["min"], axis=0),
        "max": np.max(stacked["max"], axis=0),
        "mean": mean,
        "std": np.sqrt(variance),
        "count": total,
    }
    for q in QUANTILES:
        name = f"q{round(q * 100):02d}"
        out[name] = (stacked[name] * weights).sum(axis=0) / total
    return out


# ------------------------------------------------------ many episodes at once
STAT_NAMES = ("min", "max", "mean", "std", "count", *(f"q{round(q * 100):02d}" for q in QUANTILES))
"""the statistics of one feature, in the order :func:`feature_stats` lists them"""


def segment_stats(
    features: dict[str, np.ndarray], lengths: np.ndarray
) -> dict[str, dict[str, np.ndarray]]:
    """:func:`feature_stats` of every feature (``name -> [N, ...]`` values) over consecutive
    episodes (episode ``e`` holds ``lengths[e]`` frames), vectorised: ``name -> stat ->
    [E, C]`` (``count``: ``[E, 1]``).

    min, max: segment reductions (``np.minimum.reduceat``), exact. mean, std: segment sums
    (``np.add.reduceat``) as ``ndarray.mean``/``std`` compute them (sum / n; centred squares
    summed / n; sqrt); numpy's pairwise summation may add the same numbers in another
    order, so they can differ from :func:`feature_stats` in the last bit (relative 1e-16).
    Quantiles: numpy's ``"linear"`` method on each episode sorted once
    (:func:`_segment_quantiles`), digit for digit ``np.quantile``'s."""
    lengths = np.asarray(lengths, dtype=np.int64)
    out: dict[str, dict[str, np.ndarray]] = {}
    for name, values in features.items():
        x = values[:, None] if values.ndim == 1 else values.reshape(-1, values.shape[-1])
        n = lengths * (len(x) // max(1, len(values)))  # rows of x per episode
        starts = np.concatenate([[0], np.cumsum(n)[:-1]])
        xf = x.astype(np.float64)
        mean = np.add.reduceat(xf, starts, axis=0) / n[:, None]
        centred = xf - np.repeat(mean, n, axis=0)
        out[name] = {
            "min": np.minimum.reduceat(x, starts, axis=0),
            "max": np.maximum.reduceat(x, starts, axis=0),
            "mean": mean,
            "std": np.sqrt(np.add.reduceat(centred * centred, starts, axis=0) / n[:, None]),
            "count": lengths[:, None],
            **_segment_quantiles(xf, starts, n),
        }
    return out


def _segment_quantiles(xf: np.ndarray, starts: np.ndarray, n: np.ndarray) -> dict[str, Any]:
    """Each :data:`QUANTILES` ``[E, C]`` of the consecutive segments of ``xf`` ``[M, C]``:
    the segments of lengths in ``[2^k, 2^(k+1))`` padded with +inf into one ``[E_k, L, C]``
    block (at most 2x the rows, about log2(longest) blocks), sorted along its second axis,
    then numpy 2's ``_quantile`` arithmetic on each segment's own length
    (:func:`_quantile_of_sorted`)."""
    out = {_q_name(q): np.empty((len(n), xf.shape[1])) for q in QUANTILES}
    bucket = np.ceil(np.log2(n)).astype(np.int64)
    for b in np.unique(bucket):
        episodes = np.flatnonzero(bucket == b)
        width = int(n[episodes].max())
        offsets = np.arange(width)
        valid = offsets < n[episodes][:, None]  # [E_b, L]
        block = np.full((len(episodes), width, xf.shape[1]), np.inf)
        block[valid] = xf[(starts[episodes][:, None] + offsets)[valid]]
        block.sort(axis=1)
        for q in QUANTILES:
            out[_q_name(q)][episodes] = _quantile_of_sorted(block, n[episodes], q)
    return out


def _q_name(q: float) -> str:
    return f"q{round(q * 100):02d}"


def _quantile_of_sorted(ordered: np.ndarray, n: np.ndarray, q: float) -> np.ndarray:
    """``np.quantile(segment, q, axis=0)`` of each ``[E, L, C]`` block row sorted along axis
    1, holding ``n[e]`` values, with numpy 2's own arithmetic for its default ``"linear"``
    method (virtual index ``(n - 1) * q``; at or past the last index, the last value with
    ``gamma`` taken from index -1; ``_lerp``), so that the digits are numpy's."""
    virtual = (n - 1) * q  # [E]
    previous = np.floor(virtual)
    above = virtual >= n - 1
    previous[above] = -1
    gamma = (virtual - previous)[:, None]  # [E, 1]
    lo = np.where(above, n - 1, previous).astype(np.int64)
    hi = np.where(above, n - 1, previous + 1).astype(np.int64)
    rows = np.arange(len(n))
    a, b = ordered[rows, lo], ordered[rows, hi]  # [E, C]
    diff = b - a
    return np.where(gamma >= 0.5, b - diff * (1 - gamma), a + diff * gamma)

"""``meta/stats.json`` aggregated a slice of episodes at a time, in constant memory.

:func:`~imitrl.datasets.lerobot._stats.aggregate_arrays` (lerobot 0.4's
``aggregate_feature_stats``) stacks every episode's statistics ``[E, *shape]`` and sums
over ``E``; :class:`DatasetStats` keeps running totals instead and gives the same digits.
min, max and count do not depend on the order of the episodes. The count-weighted sums
(mean, quantiles, the pooled variance) are added in numpy's own order
(:class:`EpisodeSum`). The pooled variance ``sum_e c_e (var_e + (mean_e - mean)^2) /
sum_e c_e`` needs the dataset's mean first: a second pass gives each episode's mean, std
and count again (:meth:`DatasetStats.add_spread`; :func:`save_lerobot` reads them back
from the episode table it wrote).
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import numpy as np

from imitrl.datasets.lerobot._layout import QUANTILES

BLOCK = 128
"""numpy's ``PW_BLOCKSIZE``: pairwise summation adds at most this many values directly"""
QUANTILE_NAMES = tuple(f"q{round(q * 100):02d}" for q in QUANTILES)


def _leaf_sum(x: np.ndarray) -> np.ndarray:
    """numpy's ``pairwise_sum`` of the ``n <= BLOCK`` rows of ``x [n, K]`` (each column
    apart): below 8 values, one after the other from 0.; else 8 accumulators (value ``j`` of
    every 8 into accumulator ``j``), combined as ``((r0+r1)+(r2+r3))+((r4+r5)+(r6+r7))``,
    then the rest one after the other (``numpy/_core/src/umath/loops_utils.h.src``)."""
    n = len(x)
    if n < 8:
        res = np.zeros(x.shape[1:])
        for row in x:
            res = res + row
        return res
    m = n - n % 8
    r = np.cumsum(x[:m].reshape(m // 8, 8, *x.shape[1:]), axis=0)[-1]  # [8, K], in order
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    for row in x[m:]:
        res = res + row
    return res


def _pairwise(n: int) -> Generator[int, np.ndarray, np.ndarray]:
    """numpy's pairwise summation of ``n`` rows as a coroutine: yields how many rows its
    next block needs, is sent them, returns the sum. Above :data:`BLOCK` values the rows
    split at ``n / 2`` rounded down to a multiple of 8 (numpy's split), recursively."""
    if n <= BLOCK:
        block = yield n
        return _leaf_sum(block)
    half = n // 2 - (n // 2) % 8
    left = yield from _pairwise(half)
    right = yield from _pairwise(n - half)
    return left + right


class EpisodeSum:
    """``terms.sum(axis=0)`` of ``terms [n, K]``, given a few rows at a time, with numpy's
    digits: numpy sums a ``[n, 1]`` array pairwise along ``n`` (:func:`_pairwise`) and a
    ``[n, C]`` array, ``C > 1``, row after row; ``pairwise`` says which (each column of
    ``K`` is summed apart either way). Holds fewer than :data:`BLOCK` rows."""

    def __init__(self, n: int, *, pairwise: bool) -> None:
        self._left = int(n)
        self._total: np.ndarray | None = None
        self._pending: np.ndarray | None = None  # rows not summed yet (pairwise)
        self._tree = _pairwise(self._left) if pairwise else None
        self._need = next(self._tree) if self._tree is not None else 0

    def add(self, terms: np.ndarray) -> None:
        """The next ``terms [k, K]``."""
        self._left -= len(terms)
        if self._left < 0:
            raise ValueError("more rows than the sum was declared for")
        if self._tree is None:  # row after row: cumsum adds in order
            rows = terms if self._total is None else np.concatenate([self._total[None], terms])
            self._total = np.cumsum(rows, axis=0)[-1]
            return
        rows = terms if self._pending is None else np.concatenate([self._pending, terms])
        at = 0
        while self._need and len(rows) - at >= self._need:
            block, at = rows[at : at + self._need], at + self._need
            try:
                self._need = self._tree.send(block)
            except StopIteration as done:
                self._total, self._need = done.value, 0
        self._pending = rows[at:]

    def total(self) -> np.ndarray:
        """``[K]`` the sum, once every row is added."""
        if self._left or self._total is None:
            raise ValueError(f"{self._left} rows of the sum were never added")
        return self._total


class DatasetStats:
    """Every feature's statistics over the dataset's ``E`` episodes from theirs, given in
    episode order a slice at a time: digit for digit
    :func:`~imitrl.datasets.lerobot._stats.aggregate_arrays` of them all stacked. Memory:
    a few arrays of each feature's shape, whatever ``E``.

    Pass 1, :meth:`add`: min, max, count, and the count-weighted sums of mean and
    quantiles. Pass 2, :meth:`add_spread`: the pooled variance's terms, from each episode's
    mean, std and count again. Then :meth:`result`. Features of one value per episode are
    summed together (one pairwise :class:`EpisodeSum` over all their columns: numpy sums
    each ``[E, 1]`` column pairwise), the others one :class:`EpisodeSum` each (row after
    row)."""

    def __init__(self, num_episodes: int) -> None:
        self.num_episodes = int(num_episodes)
        self._shape: dict[str, tuple[int, ...]] = {}
        self._min: dict[str, np.ndarray] = {}
        self._max: dict[str, np.ndarray] = {}
        self._count: dict[str, np.ndarray] = {}
        self._sums: dict[str, EpisodeSum] = {}  # [mean, q01, ..., q99] * count, flattened
        self._spread: dict[str, EpisodeSum] = {}  # c_e (var_e + (mean_e - mean)^2)
        self._scalar: list[str] = []  # features summed together, pairwise

    def names(self) -> list[str]:
        """The features, in the order of the first :meth:`add`."""
        return list(self._shape)

    def _start(self, stats: dict[str, dict[str, np.ndarray]]) -> None:
        for name, per in stats.items():
            self._shape[name] = shape = per["mean"].shape[1:]
            if int(np.prod(shape, dtype=np.int64)) == 1:
                self._scalar.append(name)
            else:
                self._sums[name] = EpisodeSum(self.num_episodes, pairwise=False)
                self._spread[name] = EpisodeSum(self.num_episodes, pairwise=False)
        self._sums[""] = EpisodeSum(self.num_episodes, pairwise=True)  # the scalar features
        self._spread[""] = EpisodeSum(self.num_episodes, pairwise=True)

    def _add_terms(self, sums: dict[str, EpisodeSum], terms: dict[str, np.ndarray]) -> None:
        """Each feature's ``[k, K]`` terms into its sum; the scalar features' side by side."""
        k = len(next(iter(terms.values())))
        scalar = [terms[n] for n in self._scalar]
        sums[""].add(np.concatenate(scalar, axis=1) if scalar else np.zeros((k, 0)))
        for name in self._shape:
            if name not in self._scalar:
                sums[name].add(terms[name])

    def add(self, stats: dict[str, dict[str, np.ndarray]]) -> None:
        """The next episodes' ``feature -> stat -> [k, *shape]`` (``count``: ``[k, 1]``),
        every feature (the first call fixes them and their order)."""
        if not self._shape:
            self._start(stats)
        if list(stats) != self.names():
            raise ValueError(f"features {list(stats)}, expected {self.names()}")
        terms = {}
        for name, per in stats.items():
            counts = per["count"]
            weights = counts.reshape(len(counts), *([1] * len(self._shape[name])))
            lo, hi, n = np.min(per["min"], axis=0), np.max(per["max"], axis=0), counts.sum(axis=0)
            if name in self._count:
                lo, hi = np.minimum(self._min[name], lo), np.maximum(self._max[name], hi)
                n = self._count[name] + n
            self._min[name], self._max[name], self._count[name] = lo, hi, n
            parts = [per[s] * weights for s in ("mean", *QUANTILE_NAMES)]
            terms[name] = np.concatenate([t.reshape(len(t), -1) for t in parts], axis=1)
        self._add_terms(self._sums, terms)

    def mean(self, name: str) -> np.ndarray:
        """The count-weighted mean of the episodes' means (after pass 1)."""
        shape = self._shape[name]
        if name in self._scalar:  # its 1 + len(QUANTILES) columns among the scalars'
            at = self._scalar.index(name) * (1 + len(QUANTILES))
            weighted = self._sums[""].total()[at : at + 1]
        else:
            weighted = self._sums[name].total()[: int(np.prod(shape, dtype=np.int64))]
        return (weighted / self._count[name]).reshape(shape)

    def add_spread(
        self,
        means: dict[str, np.ndarray],
        stds: dict[str, np.ndarray],
        counts: dict[str, np.ndarray],
    ) -> None:
        """Pass 2: the next episodes' ``feature -> [k, *shape]`` mean and std and ``[k, 1]``
        count, every feature: their terms ``c_e (var_e + (mean_e - mean)^2)``."""
        terms = {}
        for name in self._shape:
            weights = counts[name].reshape(len(counts[name]), *([1] * len(self._shape[name])))
            spread = (stds[name] ** 2 + (means[name] - self.mean(name)) ** 2) * weights
            terms[name] = spread.reshape(len(spread), -1)
        self._add_terms(self._spread, terms)

    def result(self, name: str) -> dict[str, Any]:
        """``min, max, mean, std, count, q01, ..., q99`` of one feature (after pass 2)."""
        shape, total = self._shape[name], self._count[name]
        size = int(np.prod(shape, dtype=np.int64))
        if name in self._scalar:
            i = self._scalar.index(name)
            sums = self._sums[""].total()[i * (1 + len(QUANTILES)) :][: 1 + len(QUANTILES)]
            spread = self._spread[""].total()[i : i + 1]
        else:
            sums, spread = self._sums[name].total(), self._spread[name].total()
        out: dict[str, Any] = {
            "min": self._min[name],
            "max": self._max[name],
            "mean": self.mean(name),
            "std": np.sqrt(spread.reshape(shape) / total),
            "count": total,
        }
        for i, q in enumerate(QUANTILE_NAMES, start=1):
            out[q] = sums[i * size : (i + 1) * size].reshape(shape) / total
        return out

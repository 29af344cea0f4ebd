"""A random permutation of ``[0, n)`` produced a batch at a time, in O(batch) memory.

Sampling without replacement usually draws ``torch.randperm(n)``: 8 bytes per row, 800
MB for a 1e8-row buffer on disk, more than the process may hold. :class:`LazyPermutation`
gives the same kind of epoch (every row exactly once, in a seeded random order) without
storing the order. The epoch is ``perm(0), perm(1), ...`` with the values ``>= n``
skipped, where ``perm`` is a 4-round Feistel network on ``2h``-bit integers
(``2^(2h) >= n``): a bijection of ``[0, 2^(2h))`` by construction, whatever its round
function, so the values below ``n`` are every row exactly once. ``2^(2h) < 4n``: a
batch of ``k`` rows maps fewer than ``4k`` positions on average. Each epoch draws its 4
round keys from the generator.

The order is a pseudo-random shuffle for minibatch SGD, not a cryptographic one, and it
differs from ``randperm``'s: a fit on a disk buffer draws other minibatches than the same
fit on an in-memory buffer (both are epochs over every row). The arithmetic is numpy
``uint64`` (wraps modulo 2^64 by definition; a few microseconds per call on a few hundred
values, where a torch op on so few values costs ~10 us).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["LazyPermutation"]

_ROUNDS = 4
_M1, _M2 = np.uint64(0xFF51AFD7ED558CCD), np.uint64(0xC4CEB9FE1A85EC53)  # murmur3 fmix64


def _mix(x: np.ndarray, key: np.uint64, mask: np.uint64) -> np.ndarray:
    """The round function, ``h`` bits -> ``h`` bits (murmur3's 64-bit finaliser)."""
    x = x ^ key
    x = (x ^ (x >> np.uint64(33))) * _M1
    x = (x ^ (x >> np.uint64(33))) * _M2
    return (x ^ (x >> np.uint64(33))) & mask


class LazyPermutation:
    """Epochs over ``[0, n)`` in seeded random order, ``take(k)`` rows at a time.

    Args:
        n: rows to permute (``1 <= n < 2^62``).
        generator: random source of the round keys (4 keys per epoch); None uses torch's
            global generator.
    """

    def __init__(self, n: int, generator: torch.Generator | None = None) -> None:
        if int(n) != n or n < 1 or n >= 1 << 62:
            raise ValueError(f"LazyPermutation needs 1 <= n < 2^62 rows, got {n!r}")
        self.n = int(n)
        self.generator = generator
        half = max(1, ((self.n - 1).bit_length() + 1) // 2)  # h: 2^(2h) >= n
        self.half, self.mask, self.domain = (
            np.uint64(half),
            np.uint64((1 << half) - 1),
            1 << 2 * half,
        )
        self.new_epoch()

    @property
    def remaining(self) -> int:
        """Rows of the current epoch not yet taken."""
        return self.n - self.taken

    def new_epoch(self) -> None:
        """Start a fresh order (draws the next epoch's round keys)."""
        draw = torch.randint(0, 1 << 62, (_ROUNDS,), generator=self.generator)
        self.keys = [np.uint64(int(k)) for k in draw]
        self.position, self.taken = 0, 0  # next domain value to map; rows handed out
        self.pending = np.empty(0, dtype=np.uint64)

    def _feistel(self, x: np.ndarray) -> np.ndarray:
        left, right = x >> self.half, x & self.mask
        for key in self.keys:
            left, right = right, left ^ _mix(right, key, self.mask)
        return (left << self.half) | right

    def take(self, k: int) -> torch.Tensor:
        """The next ``min(k, remaining)`` rows of the epoch, int64 ``[min(k, remaining)]``."""
        k = min(int(k), self.remaining)
        parts, have = [self.pending], self.pending.size
        while have < k:
            # map enough positions for the rows still wanted (2^(2h)/n of them per row)
            m = min((k - have) * self.domain // self.n + 64, self.domain - self.position)
            x = self._feistel(np.arange(self.position, self.position + m, dtype=np.uint64))
            self.position += m
            x = x[x < np.uint64(self.n)]
            parts.append(x)
            have += x.size
        rows = np.concatenate(parts)
        self.pending = rows[k:]
        self.taken += k
        return torch.from_numpy(rows[:k].astype(np.int64))

"""Explicit random streams for code that only knows the global torch RNG.

Samplers inside torch distributions (``rsample``, ``sample``) and some TorchRL
modules draw from the global generator. ``rng_from(generator)`` runs such a block on
an explicit ``torch.Generator`` instead (and advances it), so that randomness flows
from one seed and the global state is left untouched.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

__all__ = ["rng_from"]


@contextlib.contextmanager
def rng_from(generator: torch.Generator | None) -> Iterator[None]:
    """Run the block's global-RNG draws from ``generator`` (None: the global RNG itself)."""
    if generator is None:
        yield
        return
    with torch.random.fork_rng(devices=[]):
        torch.set_rng_state(generator.get_state())
        yield
        generator.set_state(torch.get_rng_state())

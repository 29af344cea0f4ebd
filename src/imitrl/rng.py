"""Explicit random streams for code that only knows the global torch RNG.

Samplers inside torch distributions (``rsample``, ``sample``) and some TorchRL
modules draw from the global generator. ``rng_from(generator)`` runs such a block on
an explicit ``torch.Generator`` instead (and advances it), so that randomness flows
from one seed and the global state is left untouched.

On a CUDA device, a draw uses the device's own global generator. Once CUDA is in use,
``rng_from`` also runs the block's CUDA draws from a CUDA stream that belongs to
``generator`` (seeded with its ``initial_seed()`` the first time, advanced by every
block after), so a sampled policy on a GPU draws the same numbers for the same seed,
run after run. The CPU generator is never drawn from for it: CPU digits are the same
whether or not a GPU is present.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

__all__ = ["SavedGenerator", "generators_kept", "rng_from"]

_CUDA_STREAMS: dict[tuple[int, int], tuple[torch.Generator, torch.Generator]] = {}
"""(id of a CPU generator, CUDA device index) -> (that generator, its CUDA stream)"""


def _cuda_stream(generator: torch.Generator, index: int) -> torch.Generator:
    entry = _CUDA_STREAMS.get((id(generator), index))
    if entry is None or entry[0] is not generator:  # a new generator (or a reused id)
        stream = torch.Generator(device=f"cuda:{index}")
        stream.manual_seed(generator.initial_seed())
        entry = _CUDA_STREAMS[(id(generator), index)] = (generator, stream)
    return entry[1]


@contextlib.contextmanager
def rng_from(generator: torch.Generator | None) -> Iterator[None]:
    """Run the block's global-RNG draws from ``generator`` (None: the global RNG itself)."""
    if generator is None:
        yield
        return
    cuda = torch.cuda.is_available() and torch.cuda.is_initialized()
    index = torch.cuda.current_device() if cuda else None
    with torch.random.fork_rng(devices=[] if index is None else [index]):
        torch.set_rng_state(generator.get_state())
        if index is not None:
            stream = _cuda_stream(generator, index)
            torch.cuda.set_rng_state(stream.get_state(), index)
        yield
        generator.set_state(torch.get_rng_state())
        if index is not None:
            stream.set_state(torch.cuda.get_rng_state(index))


class SavedGenerator:
    """For an ``nn.Module`` that draws from its own seeded ``self.generator`` (a loss's
    noise, time steps and latents; a flow or diffusion policy's sampling noise): the
    generator's state is part of the module's ``state_dict`` (its ``_extra_state``), so a
    fit, or a DAgger run, resumed from a checkpoint draws what the uninterrupted one would
    have. A state saved before the generator was
    (imitrl up to e0ceebc) lacks the key: :meth:`imitrl.learners.Learner.migrated_state`
    then keeps the freshly seeded generator, which is what those versions resumed with."""

    generator: torch.Generator

    def get_extra_state(self) -> torch.Tensor:
        """The generator's state (a ``uint8`` tensor)."""
        return self.generator.get_state()

    def set_extra_state(self, state: torch.Tensor) -> None:
        """Continue from a saved ``state`` (moved back to the CPU, where the generator
        draws, if a ``map_location`` moved it)."""
        want = self.generator.get_state()
        if (
            not isinstance(state, torch.Tensor)
            or state.dtype != torch.uint8
            or state.layout != torch.strided
            or tuple(state.shape) != tuple(want.shape)
        ):
            got = (
                f"{state.dtype} {state.layout} {list(state.shape)}"
                if isinstance(state, torch.Tensor)
                else type(state).__name__
            )
            raise ValueError(
                f"a saved generator state ({type(self).__name__}'s _extra_state) must be a "
                f"dense uint8 tensor of {want.numel()} bytes (torch.Generator.get_state), "
                f"got {got}"
            )
        self.generator.set_state(state.cpu().contiguous())


@contextlib.contextmanager
def generators_kept(module: torch.nn.Module) -> Iterator[None]:
    """Run the block, then put back the state of every :class:`SavedGenerator` in
    ``module``: a policy that samples from its own generator (a flow or diffusion policy)
    draws from it, not from an evaluation's ``seed`` or ``generator``, so two sampled
    evaluations of one learner differ unless each runs in this block (which also leaves
    the learner's stream, and what it draws next, as before)."""
    owners = [m for m in module.modules() if isinstance(m, SavedGenerator)]
    states = [m.generator.get_state() for m in owners]
    try:
        yield
    finally:
        for owner, state in zip(owners, states):
            owner.generator.set_state(state)

"""What a learner takes from a saved state dict, checked before torch copies anything.

A checkpoint may be downloaded and edited. ``torch.nn.Module.load_state_dict`` casts what
it is given to each weight's dtype and, for one weight reachable under several keys (a
policy's weights are its loss's ``actor`` too; the normaliser sits inside the policy),
keeps whichever copy it loads last. :func:`check_saved_state` refuses, naming the key:

* a value of another kind than the weight's: an integer, bool or complex value for a
  float weight, a non-bool for a flag (the cast would change it: 0.7 into an integer
  weight is 0, 0.5 into ``fitted`` is True);
* a value NaN or infinite once cast (a float64 1e300 is inf in float32);
* copies of one weight, or of one module's generator state, that differ once cast.

Only keys the module holds, at the shape it holds them, are looked at: a missing or an
unexpected key, or one of another shape, is left to torch's own check, which compares
names and shapes before it copies, so a saved view declaring 2^33 elements of one stored
value is never materialised.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["check_saved_state"]

EXTRA = "_extra_state"


def check_saved_state(module: nn.Module, state: dict) -> None:
    """ValueError (naming the key) unless ``module`` can take ``state`` as saved (module
    docstring)."""
    own = module.state_dict(keep_vars=True)
    cast: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        mine = own.get(key)
        if not (isinstance(mine, torch.Tensor) and isinstance(value, torch.Tensor)):
            continue
        if value.shape != mine.shape:
            continue  # torch names it, before copying anything
        _check_kind(key, value, mine)
        cast[key] = value.detach().to("cpu", mine.dtype)
        if cast[key].is_floating_point() and not bool(torch.isfinite(cast[key]).all()):
            once = "" if value.dtype == mine.dtype else f" once cast to {mine.dtype}"
            raise ValueError(
                f"the saved weight {key!r} holds NaN or inf{once} (the saved fit diverged, "
                "or the file was altered): nothing it does can be scored"
            )
    for names in _shared(module, own).values():
        saved = [n for n in names if n in cast]
        for name in saved[1:]:
            if not torch.equal(cast[name], cast[saved[0]]):
                raise ValueError(
                    f"the saved weights {saved[0]!r} and {name!r} are one weight of the "
                    "learner but hold different values (an edited checkpoint): refusing to "
                    "pick one"
                )


def _check_kind(key: str, value: torch.Tensor, mine: torch.Tensor) -> None:
    """ValueError unless ``value`` casts to ``mine``'s dtype without changing kind."""
    if mine.dtype == torch.bool:
        fits = value.dtype == torch.bool
    elif mine.is_floating_point():
        fits = value.is_floating_point()
    elif mine.is_complex():
        fits = value.is_complex() or value.is_floating_point()
    else:  # integers (a generator's bytes among them)
        fits = not (value.is_floating_point() or value.is_complex() or value.dtype == torch.bool)
    if not fits:
        raise ValueError(
            f"the saved weight {key!r} is {value.dtype} where the learner holds {mine.dtype}: "
            "refusing a cast that would change it (an edited checkpoint)"
        )


def _shared(module: nn.Module, own: dict) -> dict[tuple, list[str]]:
    """``module``'s state keys by what they name: one tensor (its storage, offset, dtype,
    shape and strides), or one submodule's extra state (a generator's, returned afresh
    under each key that reaches the submodule)."""
    groups: dict[tuple, list[str]] = {}
    for key, value in own.items():
        if key == EXTRA or key.endswith("." + EXTRA):
            owner = module.get_submodule(key[: -len(EXTRA)].rstrip("."))
            groups.setdefault(("extra", id(owner)), []).append(key)
        elif isinstance(value, torch.Tensor) and value.numel() > 0:
            where = (value.untyped_storage().data_ptr(), value.storage_offset(), value.dtype)
            groups.setdefault((*where, tuple(value.shape), value.stride()), []).append(key)
    return groups

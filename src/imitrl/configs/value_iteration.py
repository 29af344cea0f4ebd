"""The value-iteration expert's discount and sweeps, each declared once.

They are :func:`imitrl.experts.value_iteration_expert`'s (``--expert value_iteration``)
and the FrozenLake study's defaults (``--gamma``, ``--vi-iters``) alike; no torch is
imported, so ``--help`` reads them at once."""

from __future__ import annotations

__all__ = ["VALUE_ITERATION_GAMMA", "VALUE_ITERATION_SWEEPS"]

VALUE_ITERATION_GAMMA = 0.95
"""the discount the expert is optimal for"""

VALUE_ITERATION_SWEEPS = 1000
"""value-iteration sweeps (0.95^1000 < 1e-22: converged far below float32's resolution)"""

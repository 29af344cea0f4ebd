"""The value-iteration expert's discount and sweeps, each declared once.

The discount is :func:`imitrl.experts.value_iteration_expert`'s (``--expert
value_iteration``) and the FrozenLake study's default (``--gamma``) alike, the sweeps the
study's (``--vi-iters``); no torch is imported, so ``--help`` reads them at once."""

from __future__ import annotations

__all__ = ["VALUE_ITERATION_GAMMA", "VALUE_ITERATION_SWEEPS"]

VALUE_ITERATION_GAMMA = 0.95
"""the discount the expert is optimal for"""

VALUE_ITERATION_SWEEPS = 1000
"""the study's value-iteration sweeps (``--vi-iters``: its digits); the expert sweeps until
its values converge instead, at most the states plus ten times this"""

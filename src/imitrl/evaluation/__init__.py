"""Evaluation: Monte Carlo estimates with intervals, exact values for tabular MDPs."""

from imitrl.evaluation.evaluate import Evaluation, evaluate, mean_ci, wilson_interval
from imitrl.evaluation.tabular import exact_values, tabulate

__all__ = ["Evaluation", "evaluate", "exact_values", "mean_ci", "tabulate", "wilson_interval"]

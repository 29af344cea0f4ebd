"""Evaluation: Monte Carlo estimates with intervals, exact values for tabular MDPs."""

from imitrl.evaluation.evaluate import Evaluation, evaluate, mean_ci, wilson_interval
from imitrl.evaluation.statistics import student_t_quantile, t_interval
from imitrl.evaluation.tabular import exact_values, tabulate

__all__ = [
    "Evaluation",
    "evaluate",
    "exact_values",
    "mean_ci",
    "student_t_quantile",
    "t_interval",
    "tabulate",
    "wilson_interval",
]

"""``loss_functions.py``'s parts: ``tasks`` (the task table), ``run`` (the training
cells), ``report`` (statistics, tables, figure)."""

"""Every algorithm's settings whose command is a CLI command, one frozen dataclass each,
with its limits and its defaults, importing no torch: the library's functions take them
(``fit_bc``, ``gail``, ``airl``: :mod:`imitrl.algorithms` re-exports them) and the
command line's configs extend them (:mod:`imitrl.jobs.configs`), so that ``imitrl bc
--help`` reads every field's docstring and range without torch, and every hyperparameter
is declared once.

* :mod:`~imitrl.configs.bc`: :class:`~imitrl.configs.bc.BCConfig`, a behaviour-cloning fit.
* :mod:`~imitrl.configs.adversarial`: :class:`~imitrl.configs.adversarial.AdversarialConfig`
  and GAIL's and AIRL's, with :data:`~imitrl.configs.adversarial.ADVERSARIAL_LR`.
* :mod:`~imitrl.configs.value_iteration`: the value-iteration expert's discount and sweeps
  (the FrozenLake study's defaults too).
"""

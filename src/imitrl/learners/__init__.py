"""Learners: a policy, the loss that trains it and its optimizer, and the one place that
builds them.

* :func:`build` ``(name, env, **settings)``: the only learner builder (the command line,
  the benchmarks and the study use it): a loss-registry entry (or ``"default"``) for an
  env or a :class:`TaskSpec`; it warns (:class:`IgnoredObservationWarning`) when the
  env observes an entry the learner's policy never reads.
* :mod:`~imitrl.learners.registry`: the entries by name (:func:`registry.names`), and
  :func:`~imitrl.learners.registry.register` for your own; the built-in ones are
  registered in :mod:`~imitrl.learners.catalogue`.
* :class:`Learner`: the contract ``fit_bc``, ``dagger`` and ``evaluate`` take; an
  :class:`ActorCritic` is the table, MLP and CNN family's.
* One folder per policy family: :mod:`~imitrl.learners.actor_critic`,
  :mod:`~imitrl.learners.diffusion`, :mod:`~imitrl.learners.flow`,
  :mod:`~imitrl.learners.act`, :mod:`~imitrl.learners.diffusion_unet`; what chunked
  entries share in :mod:`~imitrl.learners.chunks`; every default width and rate in
  :mod:`~imitrl.learners.defaults`.
"""

from imitrl.learners import catalogue, registry
from imitrl.learners.actor_critic import ActorCritic
from imitrl.learners.build import DEFAULT, FOR_ENV, build, resolve
from imitrl.learners.learner import Learner
from imitrl.learners.registry import LearnerConfig
from imitrl.learners.task import IgnoredObservationWarning, TaskSpec

__all__ = [
    "DEFAULT",
    "FOR_ENV",
    "ActorCritic",
    "IgnoredObservationWarning",
    "Learner",
    "LearnerConfig",
    "TaskSpec",
    "build",
    "catalogue",
    "registry",
    "resolve",
]

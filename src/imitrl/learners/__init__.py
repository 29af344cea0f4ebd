"""Learners: a policy, the loss that trains it and its optimizer, and the one place that
builds them (the loss registry, its built-in entries registered by
:mod:`imitrl.learners.catalogue`)."""

from imitrl.learners import catalogue, registry
from imitrl.learners.actor_critic import ActorCritic
from imitrl.learners.learner import Learner

__all__ = ["ActorCritic", "Learner", "catalogue", "registry"]

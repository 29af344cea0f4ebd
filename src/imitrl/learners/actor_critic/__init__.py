"""The table, MLP and CNN family: :class:`ActorCritic` (a policy head over any spec, and a
value head when a job needs one) and the registry entries built on it."""

from imitrl.learners.actor_critic.learner import ActorCritic

__all__ = ["ActorCritic"]

"""DAgger's relabel rounds on data-parallel ranks: :class:`LeadSource`, an ``EpisodeSource``.

On ``N`` ranks (``imitrl dagger --nproc N``) every rank fits its share of each global
batch of one buffer, so every rank's buffer must grow by the same rows each round. With
``--workers`` (Ray) only rank 0 holds the workers: its source plays the round, the
workers receiving the learner's weights after each fit through TorchRL's weight sync
(``RayCollector.update_policy_weights_``, as in one process; every rank holds the same
learner after a data-parallel fit), and the round's rows are then broadcast to every rank
(:func:`~imitrl.system.ranks.from_lead`, one broadcast a round). The rows are those of
one process with the same ``--workers``: they depend on ``(seed, workers)`` alone.
"""

from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from imitrl.algorithms.dagger import EpisodeSource
from imitrl.learners.learner import Learner
from imitrl.policies.experts import Expert
from imitrl.system.ranks import from_lead, rank_and_world

__all__ = ["LeadSource"]


@dataclass
class LeadSource:
    """Rank 0's ``source`` plays; every rank gets its rows (module docstring).

    Attributes:
        source: on rank 0 the source that plays the rounds (a ``RaySource``); on another
            rank one over its own env (an ``EnvSource``), which binds the expert and checks
            the learner and is never played.
    """

    source: EpisodeSource

    def check(self, expert: Expert, learner: Learner) -> None:
        """The source's check, on every rank."""
        self.source.check(expert, learner)

    def state_dict(self) -> dict:
        """The source's (rank 0's is the one a checkpoint keeps)."""
        return self.source.state_dict()

    def load_state_dict(self, state: dict) -> None:
        """Rank 0 restores (and checks) its source's state; the others hold none that
        matters: they play nothing."""
        if rank_and_world()[0] == 0:
            self.source.load_state_dict(state)

    def collect(
        self,
        behaviour: TensorDictModuleBase,
        num_episodes: int,
        *,
        round_index: int,
        first_episode: int,
    ) -> TensorDict:
        """Rank 0's ``source.collect(...)``, on every rank."""
        rows = None
        if rank_and_world()[0] == 0:
            rows = self.source.collect(
                behaviour, num_episodes, round_index=round_index, first_episode=first_episode
            )
        return from_lead(rows)

    def close(self) -> None:
        """Close the source where it has a ``close`` (Ray workers, and Ray where it started it)."""
        close = getattr(self.source, "close", None)
        if close is not None:
            close()

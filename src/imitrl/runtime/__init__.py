"""Playing episodes: the one rollout loop, its steppers, and the seam of accelerated paths.

* :mod:`imitrl.runtime.loop`: the one rollout loop (:func:`~imitrl.runtime.loop.play`)
  that collection, relabelling and evaluation share, over a ``Stepper``.
* :mod:`imitrl.runtime.rollout`: whole expert or learner episodes as buffer rows
  (:func:`rollout_episodes`); :mod:`imitrl.runtime.returns`: per-episode returns
  (:func:`episode_returns`).
* :mod:`imitrl.runtime.reference`: the reference stepper, on public TorchRL alone.
* :mod:`imitrl.runtime.paths`: the seam that chooses between each reference and its
  accelerated form in :mod:`imitrl.runtime.fast` (the only module that imports it);
  ``with paths.reference():`` runs everything on the reference paths.
"""

from imitrl.runtime.returns import EpisodeSummary, episode_returns
from imitrl.runtime.rollout import rollout_episodes

__all__ = ["EpisodeSummary", "episode_returns", "rollout_episodes"]

"""Where a DAgger row came from: its round's beta and the learner that acted.

A LeRobot dataset of DAgger rounds (:func:`~imitrl.datasets.save_dagger_lerobot`) carries,
per frame, ``BETA`` (the probability that the round executed the expert's action) and
``POLICY_VERSION`` (the fit whose learner acted). A run that starts from such a dataset
keeps those columns in its buffer, so its own rounds must carry them too:
:func:`with_provenance` adds them to a round's rows.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from imitrl import keys

__all__ = ["NO_BETA", "with_provenance"]

NO_BETA = -1.0
"""``BETA`` of a round no coin decided (a gate handed the expert control) or whose source
did not say: not a probability, and not NaN, which no dataset reader accepts"""


def with_provenance(rows: TensorDictBase, beta: float, policy_version: int) -> TensorDictBase:
    """``rows`` ``[N]`` with ``BETA`` = ``beta`` (float32; :data:`NO_BETA` where a gate decided) and
    ``POLICY_VERSION`` = ``policy_version`` (int64) on every row, as a dataset's rows hold them."""
    n = rows.shape[0]
    rows.set(keys.BETA, torch.full((n,), float(beta), dtype=torch.float32))
    rows.set(keys.POLICY_VERSION, torch.full((n,), int(policy_version), dtype=torch.int64))
    return rows

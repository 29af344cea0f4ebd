"""``with_provenance``: a round's rows carry its beta and the learner that acted."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.data.provenance import NO_BETA, with_provenance


def test_every_row_gets_the_rounds_beta_and_policy_version():
    rows = TensorDict({keys.ROUND: torch.full((5,), 3)}, batch_size=[5])
    out = with_provenance(rows, 0.25, policy_version=2)
    assert out[keys.BETA].dtype == torch.float32 and out[keys.BETA].eq(0.25).all()
    assert out[keys.POLICY_VERSION].dtype == torch.int64 and out[keys.POLICY_VERSION].eq(2).all()
    gated = with_provenance(rows.clone(), NO_BETA, policy_version=0)
    assert gated[keys.BETA].eq(-1.0).all()  # not a probability: no coin decided

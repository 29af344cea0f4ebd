"""``check_saved_state`` (``Learner.load_state_dict``): what a learner takes from an edited
state dict. Hostile reviews: copies of one shared weight that disagreed loaded (the last
one won), also when one copy was an integer (0.7 cast to 0 matched 0); a float64 1e300
loaded as inf; bool, complex and integer weights were cast silently; a generator state's
copies were never compared; NaN weights were called "different values"."""

from __future__ import annotations

import pytest
import torch

from imitrl.envs import make_env
from imitrl.learners import build

W = "module.0.module.1.weight"


@pytest.fixture
def learner():
    return build("for_env", make_env("CartPole-v1", seed=0), hidden=(8,), seed=0)


def _state(learner):
    return {k: v.clone() for k, v in learner.state_dict().items()}


def _refused(learner, state, match):
    before = _state(learner)
    with pytest.raises(ValueError, match=match) as err:
        learner.load_state_dict(state)
    after = learner.state_dict()
    assert all(torch.equal(after[k], v) for k, v in before.items())  # nothing changed
    return str(err.value)


def test_copies_that_agree_load(learner):
    state = _state(learner)
    state["policy." + W] += 1.0
    state["loss.actor." + W] += 1.0
    learner.load_state_dict(state)
    assert torch.equal(learner.policy.module[0].module[1].weight, state["policy." + W])


def test_copies_in_another_float_dtype_that_agree_load(learner):
    state = _state(learner)
    for key in ("policy." + W, "loss.actor." + W):
        state[key] = state[key].double()
    learner.load_state_dict(state)
    assert learner.policy.module[0].module[1].weight.dtype == torch.float32


@pytest.mark.parametrize(
    ("edited", "other"),
    [("loss.actor." + W, "policy." + W), ("normalizer.scale", "policy.module.0.module.0.scale")],
)
def test_copies_that_disagree_are_refused_and_nothing_changes(learner, edited, other):
    state = _state(learner)
    state[edited] = state[edited] + 1.0
    message = _refused(learner, state, "one weight of the learner but hold different")
    assert repr(other) in message and repr(edited) in message


@pytest.mark.parametrize("first", ["policy", "loss.actor"])
def test_copies_that_agree_only_after_a_cast_are_refused(learner, first):
    """0.7 into an integer copy is 0; the other copy is 0.7: whichever loads last won."""
    state = _state(learner)
    other = "loss.actor" if first == "policy" else "policy"
    state[f"{first}.{W}"] = torch.zeros_like(state[f"{first}.{W}"], dtype=torch.int64)
    state[f"{other}.{W}"] = torch.full_like(state[f"{other}.{W}"], 0.7)
    _refused(learner, state, "is torch.int64 where the learner holds torch.float32")
    state[f"{first}.{W}"] = state[f"{other}.{W}"].half()  # 0.7 rounds in float16
    _refused(learner, state, "one weight of the learner but hold different")


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        (W, torch.ones(1, dtype=torch.bool), "is torch.bool where the learner holds torch.float32"),
        (W, torch.ones(1, dtype=torch.complex64), "is torch.complex64 where"),
        (W, torch.full((1,), 2**62, dtype=torch.int64), "is torch.int64 where"),
        (W, torch.ones(1, dtype=torch.uint8), "is torch.uint8 where"),
        (W, torch.full((1,), 1e300, dtype=torch.float64), "holds NaN or inf once cast to torch.float32"),
        (W, torch.full((1,), float("nan")), r"holds NaN or inf \(the saved fit diverged"),
        ("module.0.module.0.fitted", torch.full((1,), 0.5), "is torch.float32 where the learner holds torch.bool"),
    ],
)  # fmt: skip
def test_a_value_of_another_kind_or_not_finite_is_refused(learner, key, value, match):
    state = _state(learner)
    for prefix in ("policy.", "loss.actor.", *(("normalizer.",) if "fitted" in key else ())):
        name = prefix + key if prefix != "normalizer." else "normalizer.fitted"
        state[name] = value.reshape(()).expand(state[name].shape).clone()
    _refused(learner, state, match)


def test_a_generators_copies_that_disagree_are_refused():
    """A flow learner's sampling generator is saved under policy.* and loss.policy.*."""
    learner = build("flow", make_env("Pendulum-v1", seed=0), hidden=(8,), seed=0)
    state = {k: v.clone() for k, v in learner.state_dict().items()}
    extra = [k for k in state if k.endswith("_extra_state")]
    assert len(extra) >= 2, extra
    owners = {}
    for key in extra:
        owners.setdefault(id(learner.get_submodule(key.rsplit(".", 1)[0])), []).append(key)
    copies = next(keys for keys in owners.values() if len(keys) > 1)
    state[copies[-1]] = torch.Generator().manual_seed(12345).get_state()
    with pytest.raises(ValueError, match="one weight of the learner but hold different"):
        learner.load_state_dict(state)


def test_a_huge_view_under_an_unexpected_key_is_never_materialised(learner):
    """2^40 floats of one stored value (4 TiB if materialised): named, not allocated."""
    state = _state(learner)
    state["pad"] = torch.zeros(1).expand(2**40)
    state["policy." + W] = torch.zeros(1).expand(2**40)
    with pytest.raises(RuntimeError, match=r"size mismatch|Unexpected key"):
        learner.load_state_dict(state)

"""BehaviorCloningLoss and policy_step: exact values and the BC special case."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torchrl.data import Bounded

from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.algorithms.policy_step import policy_step
from imitrl.learners import TaskSpec, build
from imitrl.objectives import BehaviorCloningLoss


def _rows(n=64, S=8, A=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            keys.OBSERVATION: torch.randint(0, S, (n,), generator=g),
            keys.EXPERT_ACTION: torch.randint(0, A, (n,), generator=g),
        },
        [n],
    )


def _randomise(ac, seed=0):
    with torch.no_grad():
        for p in ac.policy.parameters():
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(seed)))


def test_nll_equals_cross_entropy():
    ac = build("cross_entropy", TaskSpec(action=3, num_states=8))
    _randomise(ac)
    rows = _rows()
    out = BehaviorCloningLoss(ac.policy, loss_type="nll", report_accuracy=True)(rows)
    logits = ac.policy.module[0].module.weight[rows[keys.OBSERVATION]]
    assert torch.allclose(
        out["loss_bc"], F.cross_entropy(logits, rows[keys.EXPERT_ACTION]), atol=1e-6
    )
    assert out["accuracy"] == (logits.argmax(-1) == rows[keys.EXPERT_ACTION]).float().mean()


@pytest.mark.parametrize("loss_type", ["mse", "l1", "smooth_l1"])
def test_regression_losses_equal_torch_functional(loss_type):
    spec = Bounded(-1.0, 1.0, shape=(2,))
    ac = build("for_env", TaskSpec.from_specs(3, spec), head="deterministic", hidden=(8,))
    g = torch.Generator().manual_seed(0)
    obs, label = torch.randn(32, 3, generator=g), torch.rand(32, 2, generator=g) * 2 - 1
    out = BehaviorCloningLoss(ac.policy, loss_type=loss_type)(
        TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, [32])
    )
    pred = ac.act_greedy(obs)
    ref = {"mse": F.mse_loss, "l1": F.l1_loss, "smooth_l1": F.smooth_l1_loss}[loss_type](
        pred, label
    )
    assert torch.allclose(out["loss_bc"], ref, atol=1e-6)


def test_tanh_normal_nll_is_minus_log_prob():
    spec = Bounded(-2.0, 2.0, shape=(1,))
    ac = build("for_env", TaskSpec.from_specs(3, spec), head="tanh_normal", hidden=(8,))
    obs = torch.randn(16, 3, generator=torch.Generator().manual_seed(1))
    label = torch.rand(16, 1, generator=torch.Generator().manual_seed(2)) * 3.8 - 1.9
    out = BehaviorCloningLoss(ac.policy, loss_type="nll")(
        TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, [16])
    )
    assert torch.allclose(out["loss_bc"], -ac.log_prob(obs, label).mean(), atol=1e-5)


def test_label_key_is_separate_from_the_learner_action():
    ac = build("cross_entropy", TaskSpec(action=3, num_states=8))
    rows = _rows()
    rows.set(keys.ACTION, torch.zeros(64, dtype=torch.long))
    before = rows.clone()
    BehaviorCloningLoss(ac.policy)(rows)
    assert (rows == before).all()  # the loss writes into a copy, never into the batch


def test_bad_loss_arguments():
    ac = build("cross_entropy", TaskSpec(action=3, num_states=8))
    with pytest.raises(ValueError, match="loss_type must be one of"):
        BehaviorCloningLoss(ac.policy, loss_type="hinge")
    rows = _rows()
    rows.set(keys.EXPERT_ACTION, rows[keys.EXPERT_ACTION].float())
    with pytest.raises(ValueError, match="must be integers"):
        BehaviorCloningLoss(ac.policy)(rows)


def test_policy_step_with_unit_weights_equals_one_bc_step():
    rows = _rows(n=40)
    a, b = (
        build("cross_entropy", TaskSpec(action=3, num_states=8)),
        build("cross_entropy", TaskSpec(action=3, num_states=8)),
    )
    _randomise(a, 3)
    _randomise(b, 3)
    loss_a = policy_step(a, rows, np.ones(40), action_key=keys.EXPERT_ACTION)
    fit = fit_bc(b, rows, BCConfig(num_steps=1, deduplicate=False))
    assert loss_a == pytest.approx(fit.final_loss, abs=1e-7)
    assert torch.equal(a.policy.module[0].module.weight, b.policy.module[0].module.weight)


def test_deduplicated_full_batch_fit_is_the_same_objective():
    rows = _rows(n=500, S=8, A=3)  # many repeated (state, label) pairs
    a, b = (
        build("cross_entropy", TaskSpec(action=3, num_states=8)),
        build("cross_entropy", TaskSpec(action=3, num_states=8)),
    )
    fa = fit_bc(a, rows, BCConfig(num_steps=60, deduplicate=True))
    fb = fit_bc(b, rows, BCConfig(num_steps=60, deduplicate=False))
    assert torch.allclose(fa.losses, fb.losses, atol=1e-5)
    # same objective, summed in another order: Adam's normalisation of near-zero gradients
    # amplifies rounding at the optimum, so parameters agree to 1e-2 and greedy actions exactly
    wa, wb = a.policy.module[0].module.weight, b.policy.module[0].module.weight
    assert torch.allclose(wa, wb, atol=1e-2)
    assert torch.equal(a.greedy_table(), b.greedy_table())
    with pytest.raises(ValueError, match="deduplicate=True needs integer"):
        fit_bc(
            build("for_env", TaskSpec.from_specs(2, 3)),
            TensorDict(
                {
                    keys.OBSERVATION: torch.zeros(4, 2),
                    keys.EXPERT_ACTION: torch.zeros(4, dtype=torch.long),
                },
                [4],
            ),
            BCConfig(num_steps=1, deduplicate=True),
        )


def test_policy_step_accepts_obs_act_objects_and_treats_weights_as_data():
    class Batch:
        obs = np.array([0, 1, 2, 1])
        act = np.array([1, 1, 0, 2])

    ac = build("cross_entropy", TaskSpec(action=3, num_states=3))
    adv = torch.tensor([1.0, -2.0, 0.5, 3.0], requires_grad=True)
    policy_step(ac, Batch(), adv)
    assert adv.grad is None  # no gradient reached the weights
    # the step moves log pi(a|s) along the sign of the advantage
    lp = ac.log_prob(Batch.obs, Batch.act)
    assert lp[0] > np.log(1 / 3) and lp[2] > np.log(1 / 3)
    with pytest.raises(ValueError, match="one weight per row"):
        policy_step(ac, Batch(), np.ones(3))
    with pytest.raises(ValueError, match="NaN"):
        policy_step(ac, Batch(), np.array([1.0, np.nan, 1.0, 1.0]))


@pytest.mark.parametrize(
    ("label", "match"),
    [
        (torch.tensor([0, 1, 5, 2]), r"label 5 under 'expert_action' is outside \[0, 3\)"),
        (torch.tensor([0, -1, 1, 2]), r"label -1 under 'expert_action' is outside"),
        (torch.tensor([[0], [1], [2], [1]]), "one integer per row"),
        (torch.tensor([0.0, 1.0, 2.0, 1.0]), "must be integers"),
    ],
)
def test_fit_rejects_bad_categorical_labels(label, match):
    rows = TensorDict(
        {keys.OBSERVATION: torch.tensor([0, 1, 2, 3]), keys.EXPERT_ACTION: label}, [4]
    )
    for cfg in (BCConfig(num_steps=1), BCConfig(num_steps=1, batch_size=2)):
        with pytest.raises(ValueError, match=match):
            fit_bc(build("cross_entropy", TaskSpec(action=3, num_states=8)), rows, cfg)


def test_fit_rejects_non_finite_continuous_labels():
    spec = Bounded(-1.0, 1.0, shape=(2,))
    rows = TensorDict(
        {
            keys.OBSERVATION: torch.zeros(3, 4),
            keys.EXPERT_ACTION: torch.tensor([[0.0, 0.1], [float("nan"), 0.0], [0.2, 0.2]]),
        },
        [3],
    )
    with pytest.raises(ValueError, match="NaN or inf"):
        fit_bc(
            build("for_env", TaskSpec.from_specs(4, spec), head="deterministic", loss="mse"),
            rows,
            BCConfig(num_steps=1),
        )


def test_log_prob_rejects_out_of_range_actions():
    ac = build("cross_entropy", TaskSpec(action=3, num_states=4))
    with pytest.raises(ValueError, match=r"lie in \[0, 3\)"):
        ac.log_prob(np.array([0, 1]), np.array([0, 7]))


def test_tanh_normal_nll_of_labels_on_the_bounds_is_finite_and_pulls_towards_them():
    spec = Bounded(-2.0, 2.0, shape=(1,))
    ac = build("for_env", TaskSpec.from_specs(3, spec), head="tanh_normal", hidden=(8,), lr=1e-2)
    rows = TensorDict(
        {keys.OBSERVATION: torch.zeros(64, 3), keys.EXPERT_ACTION: torch.full((64, 1), 2.0)}, [64]
    )
    fit = fit_bc(ac, rows, BCConfig(num_steps=200))
    assert torch.isfinite(fit.losses).all() and fit.losses[0] < 1.0  # not TorchRL's clamped -log(0)
    assert (
        float(ac.act_greedy(np.zeros((1, 3), np.float32))[0, 0]) > 1.99
    )  # mode driven to the bound
    with pytest.raises(ValueError, match="bound_margin"):
        BehaviorCloningLoss(ac.policy, bound_margin=0.7)

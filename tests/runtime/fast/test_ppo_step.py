"""The PPO and discriminator steps' accelerated pieces, each against its reference, bit for bit.

A tanh-normal's log-probability with its action-only part computed once per batch, the
loss on a minibatch's tensors for every probabilistic head, Adam over several optimizers
as one flat call, the gradient clip's four calls, GAIL's discriminator loss on tensors,
TorchRL's safe tanh without ``Function.apply`` when nothing records a gradient.
"""

from __future__ import annotations

import contextlib
import copy

import pytest
import torch
from torch import distributions as D
from torchrl.modules import TanhNormal
from torchrl.modules.distributions.utils import safetanh_noeps

from imitrl.algorithms.adversarial.gail_discriminator import GAILDiscriminator
from imitrl.algorithms.adversarial.generator import PPOGenerator
from imitrl.algorithms.adversarial.transitions import sample_rows
from imitrl.compat import safe_tanh
from imitrl.envs import make_env
from imitrl.learners import build
from imitrl.runtime import paths
from imitrl.runtime.fast.adam_step import optimizer_step
from imitrl.runtime.fast.clip_grad import clip_grad_norm
from imitrl.runtime.fast.tanh_normal import TanhNormalLogProb
from tests.algorithms.adversarial.test_loop_lanes import _round_batch


def _bounds(dim: int, kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    if kind == "unit":
        return -torch.ones(dim), torch.ones(dim)
    if kind == "pendulum":
        return torch.full((dim,), -2.0), torch.full((dim,), 2.0)
    low = torch.linspace(-3.0, -0.5, dim)
    return low, low + torch.linspace(0.25, 4.0, dim)  # asymmetric, every span its own


@pytest.mark.parametrize(("dim", "kind"), [(1, "pendulum"), (3, "unit"), (6, "mixed")])
@pytest.mark.parametrize("scale_shape", ["rows", "shared"])
def test_tanh_normal_log_prob_is_the_distributions(dim, kind, scale_shape):
    """Value and gradients of ``TanhNormal(loc, scale, low, high).log_prob(a)`` on
    minibatches of a batch (97 rows: a scalar tail on every width), actions on and next to
    the bounds included (where the safe atanh clamps)."""
    g = torch.Generator().manual_seed(dim)
    low, high = _bounds(dim, kind)
    n = 400
    u = torch.rand(n, dim, generator=g)
    u[:8] = torch.tensor([0.0, 1.0, 1e-7, 1 - 1e-7, 0.5, 0.0, 1.0, 0.25])[:, None]
    actions = low + (high - low) * u
    scorer = TanhNormalLogProb.of(TanhNormal, ["loc", "scale"], {"low": low, "high": high})
    assert scorer is not None
    for rows in (torch.arange(n), torch.randperm(n, generator=g)[:97], torch.tensor([3])):
        loc = (3 * torch.randn(len(rows), dim, generator=g)).requires_grad_()
        shape = (len(rows), dim) if scale_shape == "rows" else (1, dim)
        log_std = torch.randn(shape, generator=g).requires_grad_()
        weights = torch.randn(len(rows), generator=g)
        grads = []
        for fast in (False, True):
            scale = (
                log_std.exp().expand(len(rows), dim) if scale_shape == "shared" else log_std.exp()
            )
            if fast:
                out = scorer(loc, scale, actions[rows])
            else:
                out = TanhNormal(loc, scale, low=low, high=high).log_prob(actions[rows])
            (out * weights).sum().backward()
            grads.append((out.detach(), loc.grad, log_std.grad))
            loc.grad = log_std.grad = None
        for a, b in zip(*grads):
            assert a.shape == b.shape and torch.equal(a, b)


def test_tanh_normal_log_prob_steps_aside_where_it_would_compute_otherwise():
    kwargs = {"low": -torch.ones(2), "high": torch.ones(2)}
    assert TanhNormalLogProb.of(TanhNormal, ["loc", "scale"], kwargs) is not None
    assert TanhNormalLogProb.of(TanhNormal, ["loc", "scale"], {"low": -1.0}) is None
    assert TanhNormalLogProb.of(TanhNormal, ["loc", "scale"], {**kwargs, "tanh_loc": True}) is None
    D.Distribution.set_default_validate_args(True)
    try:  # the distribution checks its input: it is built
        assert TanhNormalLogProb.of(TanhNormal, ["loc", "scale"], kwargs) is None
    finally:
        D.Distribution.set_default_validate_args(False)  # torchrl's default, set at import


_HEADS = [
    ("Pendulum-v1", "tanh_normal"),
    ("Pendulum-v1", "tanh_normal_free"),
    ("Pendulum-v1", "normal"),
    ("Pendulum-v1", "normal_free"),
    ("CartPole-v1", "categorical"),
]


@pytest.mark.parametrize(("env_id", "head"), _HEADS)
def test_the_loss_on_tensors_is_clip_ppo_loss_for_every_head(env_id, head):
    """``TensorPPO`` on a minibatch's columns against ``ClipPPOLoss`` on its rows: both
    losses and every parameter's gradient."""
    batch, _ = _round_batch(env_id, 2)
    env = make_env(env_id, seed=0)
    learner = build("for_env", env, head=head, hidden=(16, 16), seed=0, value=True)
    generator = PPOGenerator(learner, gamma=0.99, gae_lambda=0.95, clip_epsilon=0.2,
                             entropy_coeff=0.0, epochs=1, minibatch_size=32,
                             max_grad_norm=0.5)  # fmt: skip
    loss = generator.loss
    with torch.no_grad():
        batch.set(loss.tensor_keys.sample_log_prob,
                  learner.get_dist(batch).log_prob(batch.get("action")) - 0.1)  # fmt: skip
        generator.gae(batch)
    flat = batch.reshape(-1)
    fast = paths.ppo_loss(loss, flat)
    assert fast.accelerated
    with paths.reference("ppo_loss"):
        reference = paths.ppo_loss(loss, flat)
    assert not reference.accelerated
    assert (fast.tanh_normal is not None) == head.startswith("tanh_normal")
    drawn = torch.randperm(flat.numel(), generator=torch.Generator().manual_seed(2))
    params = generator.params
    # a minibatch of 32, and of one row (a rollout's last when one row is left over: TorchRL
    # leaves its advantage as it is, where the accelerated piece used to divide by a NaN std)
    for rows in (drawn[:32], drawn[:1]):
        results = []
        for piece in (reference, fast):
            out = piece.on_rows(piece.prepare(flat), rows)
            assert sorted(out) == ["loss_critic", "loss_objective"]
            sum(out.values()).backward()
            results.append(([out[k].detach() for k in sorted(out)], [p.grad for p in params]))
            for p in params:
                p.grad = None
        (ref_losses, ref_grads), (losses, grads) = results
        assert all(bool(torch.isfinite(x).all()) for x in [*ref_losses, *ref_grads])
        assert all(torch.equal(a, b) for a, b in zip(losses, ref_losses))
        assert all(torch.equal(a, b) for a, b in zip(grads, ref_grads))


def _two_nets(seed: int = 0) -> tuple[torch.nn.Module, torch.nn.Module]:
    torch.manual_seed(seed)
    pi = torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2))
    v = torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1))
    return pi, v


def _ppo_like(pi, v, opts, step, clip, steps: int = 40, *, lr_split: tuple = (),
              skip_at: int = -1, reload_at: int = -1) -> list[torch.Tensor]:  # fmt: skip
    g = torch.Generator().manual_seed(5)
    params = [*pi.parameters(), *v.parameters()]
    norms = []
    for k in range(steps):
        x = torch.randn(8, 3, generator=g)
        loss = pi(x).sin().pow(2).mean() + v(x).cos().mean() * 10.0 ** (k % 3)
        for p in params:
            p.grad = None
        loss.backward()
        if k == skip_at:  # the value head gets no gradient this step: each optimizer's own step
            for p in v.parameters():
                p.grad = None
        if k in lr_split:  # the settings part (then agree again): each steps on its own
            opts[1].param_groups[0]["lr"] *= 0.5 if k == lr_split[0] else 2.0
        if k == reload_at:  # the state replaced under the step: read afresh
            for o in opts:
                o.load_state_dict(copy.deepcopy(o.state_dict()))
        norms.append(clip(params, 0.5))
        step()
    return norms


@pytest.mark.parametrize(
    "kwargs",
    [{}, {"foreach": False}, {"amsgrad": True, "weight_decay": 1e-2},
     {"maximize": True, "betas": (0.8, 0.99), "eps": 1e-6}],
)  # fmt: skip
@pytest.mark.parametrize("events", [{}, {"lr_split": (25, 29)}, {"skip_at": 12}, {"reload_at": 9}])
def test_adam_over_two_optimizers_as_one_flat_call_is_their_own_steps(kwargs, events):
    ref_nets, fast_nets = _two_nets(), _two_nets()
    ref_opts = [torch.optim.Adam(n.parameters(), lr=1e-2, **kwargs) for n in ref_nets]
    fast_opts = [torch.optim.Adam(n.parameters(), lr=1e-2, **kwargs) for n in fast_nets]

    def ref_step():
        for o in ref_opts:
            o.step()

    step = optimizer_step(*fast_opts)
    ref_norms = _ppo_like(*ref_nets, ref_opts, ref_step, torch.nn.utils.clip_grad_norm_, **events)
    norms = _ppo_like(*fast_nets, fast_opts, step, clip_grad_norm, **events)
    # the flat call ran to the end, except after a skipped gradient (step counts differ)
    assert (step.layouts is not None) == ("skip_at" not in events)
    assert all(torch.equal(a, b) for a, b in zip(norms, ref_norms))
    for a, b in zip(ref_nets, fast_nets):
        assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))
    for a, b in zip(ref_opts, fast_opts):  # the optimizers' own state: the same values
        sa, sb = a.state_dict(), b.state_dict()
        assert sa["param_groups"] == sb["param_groups"]
        for i in sa["state"]:
            s, t = sa["state"][i], sb["state"][i]
            assert s.keys() == t.keys() and all(torch.equal(s[k], t[k]) for k in s)


def test_groups_changed_shared_parameters_and_one_tensor_take_adams_own_steps():
    """A group added after the step was made, a parameter in both optimizers (the flat
    call would update it once), a single tensor: the per-optimizer steps, Adam's bits."""
    runs = []
    for fast in (False, True):
        torch.manual_seed(0)
        shared = torch.nn.Parameter(torch.randn(4))
        a, b = torch.nn.Parameter(torch.randn(3)), torch.nn.Parameter(torch.randn(5))
        extra = torch.nn.Parameter(torch.randn(2))
        opts = [torch.optim.Adam([a, shared], lr=0.1), torch.optim.Adam([b, shared], lr=0.1)]
        lone = torch.nn.Parameter(torch.randn(6))
        lone_opt = torch.optim.Adam([lone], lr=0.1)
        steps = [optimizer_step(*opts), optimizer_step(lone_opt)] if fast else [
            lambda opts=opts: [o.step() for o in opts], lone_opt.step]  # fmt: skip
        for k in range(8):
            if k == 4:
                opts[0].add_param_group({"params": [extra]})
            for p in (a, b, shared, extra, lone):
                p.grad = torch.full_like(p, float(k + 1)).sin()
            for s in steps:
                s()
        runs.append([t.detach().clone() for t in (a, b, shared, extra, lone)])
        if fast:
            assert not hasattr(steps[0], "layouts")  # the shared parameter: no flat call
    assert all(torch.equal(x, y) for x, y in zip(*runs))
    nets = _two_nets()
    opts = [torch.optim.Adam(n.parameters(), lr=1e-2) for n in nets]
    step = optimizer_step(*opts)
    _ppo_like(*nets, opts, step, clip_grad_norm, steps=6)
    opts[0].add_param_group({"params": [torch.nn.Parameter(torch.zeros(2))]})
    assert not step._current()  # two groups: Adam's own step from here on


def test_each_optimizers_state_keeps_its_own_buffers():
    """One optimizer's saved state holds its own moments only (views of its own flat
    buffers, not of a buffer shared with the other optimizer)."""
    nets = _two_nets()
    opts = [torch.optim.Adam(n.parameters(), lr=1e-2) for n in nets]
    _ppo_like(*nets, opts, optimizer_step(*opts), clip_grad_norm, steps=3)
    for net, opt in zip(nets, opts):
        own = sum(p.numel() for p in net.parameters()) * 4  # float32 bytes per moment
        storages = {
            t.untyped_storage().data_ptr(): t.untyped_storage().nbytes()
            for st in opt.state_dict()["state"].values()
            for k, t in st.items()
            if k != "step"
        }
        assert sorted(storages.values()) == [own, own]  # exp_avg, exp_avg_sq


def test_the_flat_state_is_the_optimizers_state():
    """The moments live in flat buffers whose views are ``opt.state``: Adam's own step
    afterwards, a deep copy and a state-dict round trip all read and write the same values."""
    nets = _two_nets()
    opts = [torch.optim.Adam(n.parameters(), lr=1e-2) for n in nets]
    _ppo_like(*nets, opts, optimizer_step(*opts), clip_grad_norm, steps=5)
    twin_nets = copy.deepcopy(nets)
    twin_opts = [torch.optim.Adam(n.parameters(), lr=1e-2) for n in twin_nets]
    for a, b in zip(opts, twin_opts):
        b.load_state_dict(copy.deepcopy(a.state_dict()))
    step_twin = lambda: [o.step() for o in twin_opts]  # noqa: E731
    _ppo_like(*nets, opts, lambda: [o.step() for o in opts], clip_grad_norm, steps=5)
    _ppo_like(*twin_nets, twin_opts, step_twin, clip_grad_norm, steps=5)
    for a, b in zip(nets, twin_nets):
        assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))


def test_the_clip_falls_back_where_it_would_group_otherwise():
    a = torch.nn.Parameter(torch.randn(4))
    b = torch.nn.Parameter(torch.randn(3, dtype=torch.float64))
    a.grad, b.grad = torch.randn(4) * 9, torch.randn(3, dtype=torch.float64) * 9
    ref = [a.grad.clone(), b.grad.clone()]
    norm = clip_grad_norm([a, b], 1.0)  # two dtypes: two groups, torch's own call
    pa, pb = torch.nn.Parameter(a.detach().clone()), torch.nn.Parameter(b.detach().clone())
    pa.grad, pb.grad = ref
    assert torch.equal(norm, torch.nn.utils.clip_grad_norm_([pa, pb], 1.0))
    assert torch.equal(a.grad, pa.grad) and torch.equal(b.grad, pb.grad)
    c = torch.nn.Parameter(torch.randn(2))  # no gradient: skipped as torch skips it
    assert torch.equal(clip_grad_norm([c], 1.0), torch.nn.utils.clip_grad_norm_([c], 1.0))


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
def test_the_discriminator_step_is_the_same_on_both_paths(env_id):
    """Ten GAIL discriminator updates through ``GAILLoss`` and through its tensor form:
    the same metrics and weights; the penalised loss keeps the module."""
    batch, learner = _round_batch(env_id, 2)
    from imitrl.algorithms.adversarial.transitions import policy_transitions

    rows = policy_transitions(batch)
    expert = rows[torch.randperm(rows.shape[0], generator=torch.Generator().manual_seed(3))]
    runs = []
    for fast in (True, False):
        disc = GAILDiscriminator(learner, hidden=(16, 16), seed=1)
        g = torch.Generator().manual_seed(4)
        with contextlib.nullcontext() if fast else paths.reference():
            assert paths.gail_loss(disc.loss).accelerated == fast
            metrics = [disc.update(sample_rows(expert, 32, g), sample_rows(rows, 32, g))
                       for _ in range(10)]  # fmt: skip
        runs.append((metrics, [p.detach().clone() for p in disc.params]))
    (m_fast, w_fast), (m_ref, w_ref) = runs
    assert m_fast == m_ref and all(torch.equal(a, b) for a, b in zip(w_fast, w_ref))
    penalised = GAILDiscriminator(learner, hidden=(16, 16), grad_penalty=1.0)
    assert not paths.gail_loss(penalised.loss).accelerated


def test_safe_tanh_is_torchrls_with_and_without_a_gradient():
    x = torch.cat([torch.randn(200) * 4, torch.tensor([0.0, 9.0, -9.0, 30.0, -30.0, 1e-8])])
    with torch.no_grad():
        assert torch.equal(safe_tanh(x), safetanh_noeps(x))
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    ya, yb = safe_tanh(xa), safetanh_noeps(xb)
    assert ya.grad_fn is not None and torch.equal(ya, yb)
    w = torch.randn(x.shape)
    (ya * w).sum().backward()
    (yb * w).sum().backward()
    assert torch.equal(xa.grad, xb.grad)


@pytest.mark.parametrize("shape", [(8, 2), (5, 3, 4), (7,)])
def test_the_categorical_draw_and_log_prob_are_the_distributions(shape):
    from imitrl.policies.distributions import GreedyCategorical
    from imitrl.runtime.fast import categorical

    g = torch.Generator().manual_seed(len(shape))
    logits = (torch.randn(shape, generator=g) * 5).requires_grad_()
    torch.manual_seed(11)
    ref = GreedyCategorical(logits).sample()
    torch.manual_seed(11)
    draw = categorical.sample(logits.detach())
    assert draw.shape == ref.shape and torch.equal(draw, ref)
    assert not torch.equal(torch.get_rng_state(), torch.manual_seed(11).get_state())  # it drew
    action = torch.randint(shape[-1], shape[:-1], generator=g)
    out = [GreedyCategorical(logits).log_prob(action), categorical.log_prob(logits, action)]
    grads = []
    for lp in out:
        (lp * torch.arange(lp.numel()).reshape(lp.shape)).sum().backward()
        grads.append(logits.grad)
        logits.grad = None
    assert torch.equal(out[0], out[1]) and torch.equal(*grads)
    assert categorical.replays(GreedyCategorical, ["logits"], {})
    assert not categorical.replays(torch.distributions.Categorical, ["logits"], {})

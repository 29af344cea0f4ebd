"""The fit's optimizer step: Adam's own update to the bit, and Adam itself where it must."""

from __future__ import annotations

import copy

import pytest
import torch

from imitrl.learners import build
from imitrl.runtime.fast.adam_step import optimizer_step


def _net() -> torch.nn.Module:
    torch.manual_seed(0)
    return torch.nn.Sequential(
        torch.nn.Linear(3, 16),
        torch.nn.Tanh(),
        torch.nn.Linear(16, 16),
        torch.nn.Tanh(),
        torch.nn.Linear(16, 2),
    )


def _train(net, opt, step, steps: int = 60, lr_every: int = 0, skip_last: bool = False):
    g = torch.Generator().manual_seed(1)
    for k in range(steps):
        x = torch.randn(8, 3, generator=g)
        opt.zero_grad(set_to_none=True)
        out = net(x)
        # skip_last: the last layer gets no gradient on odd steps (Adam skips it there)
        loss = (out[:, :1] if skip_last and k % 2 else out).sin().pow(2).mean()
        if skip_last and k % 2:
            loss = loss + 0 * sum(p.sum() for p in net[:-1].parameters())
        loss.backward()
        if skip_last and k % 2:
            for p in net[-1].parameters():
                p.grad = None
        if lr_every and k % lr_every == 0:
            for group in opt.param_groups:
                group["lr"] *= 0.7  # a schedule: read at every step
        step()


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"foreach": False},
        {"amsgrad": True, "weight_decay": 1e-2},
        {"maximize": True, "betas": (0.8, 0.99), "eps": 1e-6},
        {"weight_decay": 1e-2, "decoupled_weight_decay": True},
    ],
)
@pytest.mark.parametrize("skip_last", [False, True])
def test_the_step_is_adams_to_the_bit(kwargs, skip_last):
    a, b = _net(), _net()
    opt_a = torch.optim.Adam(a.parameters(), lr=1e-2, **kwargs)
    opt_b = torch.optim.Adam(b.parameters(), lr=1e-2, **kwargs)
    _train(a, opt_a, opt_a.step, lr_every=7, skip_last=skip_last)
    _train(b, opt_b, optimizer_step(opt_b), lr_every=7, skip_last=skip_last)
    for p, q in zip(a.parameters(), b.parameters()):
        assert torch.equal(p, q)
    for s, t in zip(opt_a.state.values(), opt_b.state.values()):
        assert s.keys() == t.keys() and all(torch.equal(s[k], t[k]) for k in s)


def test_other_optimizers_hooks_and_groups_keep_their_own_step():
    net = _net()
    sgd = torch.optim.SGD(net.parameters(), lr=0.1)
    assert optimizer_step(sgd) == sgd.step
    fused = torch.optim.Adam(net.parameters(), lr=0.1, fused=True)
    assert optimizer_step(fused) == fused.step
    groups = torch.optim.Adam(
        [{"params": net[0].parameters()}, {"params": net[2].parameters(), "lr": 0.5}], lr=0.1
    )
    assert optimizer_step(groups) == groups.step
    patched = torch.optim.Adam(net.parameters(), lr=0.1)
    patched.step = lambda: None  # an instance's own step (a test's recorder, say) runs
    assert optimizer_step(patched) is patched.step
    # a hook registered after the step was made: the step sees it and calls Adam's own
    adam = torch.optim.Adam(net.parameters(), lr=0.1)
    step, calls = optimizer_step(adam), []
    adam.register_step_post_hook(lambda *args: calls.append(1))
    net(torch.randn(2, 3)).sum().backward()
    step()
    step()
    assert calls == [1, 1]


def test_a_fit_trains_as_plain_adam_steps_do():
    from imitrl.algorithms import BCConfig, fit_bc
    from imitrl.envs import make_env
    from imitrl.experts import pendulum_expert
    from imitrl.runtime import paths, rollout_episodes

    env = make_env("Pendulum-v1", seed=0)
    rows = rollout_episodes(env, pendulum_expert(), 1)
    fast = build("for_env", env, hidden=(16, 16), seed=0, value=True)
    plain = copy.deepcopy(fast)
    fit_bc(fast, rows, BCConfig(40, batch_size=16, seed=0))
    with paths.reference():  # opt.step (and the loss's reference form)
        fit_bc(plain, rows, BCConfig(40, batch_size=16, seed=0))
    for p, q in zip(fast.policy.parameters(), plain.policy.parameters()):
        assert torch.equal(p, q)

"""The seam (:mod:`imitrl.runtime.paths`) itself, and fits through it.

* the seam: no module outside it imports the accelerated internals, one rollout loop
  plays every episode, and ``paths.reference()`` takes every reference path;
* fits: every registry loss (discrete, continuous, chunked, pixel) fitted with the
  accelerated loss form and optimizer step against a fit inside ``paths.reference()``.

The rollouts' and evaluations' agreement is ``test_paths.py``'s.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data.chunks import add_chunk_labels
from imitrl.envs import make_env
from imitrl.envs.pixel_tasks import PixelBalanceEnv, balance_expert
from imitrl.experts import cartpole_expert
from imitrl.learners import build, registry
from imitrl.runtime import episode_returns, paths, rollout_episodes
from tests.learners.test_registry import TASKS, _cases, _rows
from tests.runtime.test_paths import assert_same

DET = ExplorationType.DETERMINISTIC

SRC = Path(__file__).resolve().parents[2] / "src" / "imitrl"


def _imports(path: Path) -> set[str]:
    """The modules ``path`` imports (``from a import b`` gives ``a`` and ``a.b``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
    return found


def test_only_the_seam_imports_the_accelerated_internals():
    inside = {SRC / "runtime" / "paths.py", *(SRC / "runtime" / "fast").rglob("*.py")}
    outside = [
        str(path.relative_to(SRC))
        for path in SRC.rglob("*.py")
        if path not in inside
        and any(
            m == "imitrl.runtime.fast" or m.startswith("imitrl.runtime.fast.")
            for m in _imports(path)
        )
    ]
    assert outside == []
    # and the seam does import each of them (the grep above could pass on a renamed
    # package); policy_call is the accelerated stepper's, reached through it
    seam = _imports(SRC / "runtime" / "paths.py")
    for module in (
        "env_steps",
        "stepper",
        "toy_text",
        "tensor_chain",
        "adam_step",
        "ppo_step",
    ):
        assert f"imitrl.runtime.fast.{module}" in seam


def test_one_rollout_loop_steps_every_env():
    """TorchRL's step call appears once, in the reference stepper; the direct step once, in
    the accelerated one; and only the loop calls a stepper's step (in ``play``, for whole
    episodes, and ``play_steps``, for an on-policy learner's fixed-step batches)."""
    calls: dict[str, list[str]] = {"step_and_maybe_reset": [], "step_raw": [], ".step()": []}
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                name = node.func.attr
                if name in ("step_and_maybe_reset", "step_raw"):
                    calls[name].append(str(path.relative_to(SRC)))
                if name == "step" and getattr(node.func.value, "id", None) == "stepper":
                    calls[".step()"].append(str(path.relative_to(SRC)))
    assert calls == {
        "step_and_maybe_reset": ["runtime/reference.py"],
        "step_raw": ["runtime/fast/stepper.py"],
        ".step()": ["runtime/loop.py", "runtime/loop.py"],
    }


def test_the_reference_context_takes_every_reference_path():
    env = make_env("CartPole-v1", seed=0)
    policy = cartpole_expert().as_actor()
    with set_exploration_type(DET):
        assert type(paths.stepper(env, policy, record=False)).__name__ == "DirectStepper"
        with paths.reference("stepper"):
            assert type(paths.stepper(env, policy, record=False)).__name__ == "TorchRLStepper"
            assert paths.fast_enabled("ppo_loss") and not paths.fast_enabled()
        with paths.reference():
            assert not paths.fast_enabled()
            assert type(paths.stepper(env, policy, record=False)).__name__ == "TorchRLStepper"
            net = torch.nn.Linear(2, 2)
            opt = torch.optim.Adam(net.parameters())
            assert paths.optimizer_step(opt) == opt.step
        assert paths.fast_enabled()
        assert paths.optimizer_step(opt) != opt.step


def test_rollouts_inside_the_reference_context_equal_the_fast_ones():
    def run():
        env = make_env("CartPole-v1", seed=0, num_envs=2)
        rows = rollout_episodes(env, cartpole_expert(), 3, seed=4)
        return rows, episode_returns(env, cartpole_expert(), 5, seed=5)

    fast = run()
    with paths.reference():
        slow = run()
    for a, b in zip(fast, slow):
        assert_same(a, b)


@pytest.mark.parametrize(("name", "tname"), list(_cases()))
def test_every_registry_loss_fits_to_the_bit_on_both_paths(name, tname):
    task = TASKS[tname]
    horizon = registry.get(name).horizon
    rows = _rows(task) if horizon is None else add_chunk_labels(_rows(task), horizon)

    def fit() -> tuple[torch.Tensor, list[torch.Tensor]]:
        learner = build(name, task, shared=dict(hidden=(16, 16), lr=1e-2, seed=0))
        result = fit_bc(learner, rows, BCConfig(num_steps=6, batch_size=16, seed=0))
        return result.losses, [p.detach().clone() for p in learner.policy.parameters()]

    fast_losses, fast_params = fit()
    with paths.reference():
        slow_losses, slow_params = fit()
    assert torch.equal(fast_losses, slow_losses)
    assert all(torch.equal(a, b) for a, b in zip(fast_params, slow_params))


def test_a_pixel_fit_is_the_same_on_both_paths():
    env = PixelBalanceEnv(pixels=(16, 16), batch_size=(2,), seed=0)
    rows = rollout_episodes(env, balance_expert(), 2)

    def fit():
        learner = build("for_env", env, channels=(4,), hidden=(16,), seed=0)
        losses = fit_bc(learner, rows, BCConfig(num_steps=3, batch_size=32, seed=0)).losses
        return losses, episode_returns(env, learner.policy, 2, exploration=DET, seed=1).returns

    fast = fit()
    with paths.reference():
        slow = fit()
    for a, b in zip(fast, slow):
        assert torch.equal(a, b)

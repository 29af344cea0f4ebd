"""A fit's losses reach the logger and the progress bar while it runs (issue 44: they
reached the logger only when the fit ended, so a long ``diffusion_unet`` fit showed
nothing and a killed one left no curve); what is logged does not depend on when."""

from __future__ import annotations

import io

import torch
from tensordict import TensorDict

from imitrl.algorithms import BCConfig, bc, fit_bc
from imitrl.learners import TaskSpec, build


class Recorder:
    """A logger recording each scalar with the Adam step count the learner had reached."""

    def __init__(self, opt: torch.optim.Optimizer) -> None:
        self.opt, self.calls = opt, []

    def log_scalar(self, name: str, value: float, step: int) -> None:
        state = next(iter(self.opt.state.values()), {})
        self.calls.append((name, step, value, int(state.get("step", 0))))


def _fit(monkeypatch, flush_seconds: float, **kwargs):
    monkeypatch.setattr(bc, "FLUSH_SECONDS", flush_seconds)
    g = torch.Generator().manual_seed(0)
    rows = TensorDict({"observation": torch.randn(64, 3, generator=g),
                       "expert_action": torch.randint(0, 2, (64,), generator=g)}, [64])  # fmt: skip
    learner = build("cross_entropy", TaskSpec(action=2, observation_dim=3), hidden=(8,))
    logger = Recorder(learner.opt_pi)
    result = fit_bc(learner, rows, BCConfig(num_steps=30, batch_size=16), logger=logger,
                    log_step=100, **kwargs)  # fmt: skip
    return result, logger.calls


def test_losses_are_logged_during_the_fit_each_at_its_step(monkeypatch):
    result, calls = _fit(monkeypatch, 0.0)  # a flush after every step
    assert [c[1] for c in calls] == list(range(100, 130))
    assert [c[2] for c in calls] == result.losses.tolist()
    # the logger had the loss of step k while Adam was at step k + 1, not at the end
    assert [c[3] for c in calls] == list(range(1, 31))


def test_what_is_logged_does_not_depend_on_when(monkeypatch):
    streamed, live = _fit(monkeypatch, 0.0)
    batched, at_end = _fit(monkeypatch, 1e9)  # never due: everything at the end
    assert [c[:3] for c in live] == [c[:3] for c in at_end]
    assert {c[3] for c in at_end} == {30}
    assert torch.equal(streamed.losses, batched.losses)


def test_the_progress_bar_shows_the_latest_loss(monkeypatch):
    import tqdm.auto

    shown = io.StringIO()
    real = tqdm.auto.tqdm
    monkeypatch.setattr(
        bc, "tqdm", lambda *a, **k: real(*a, **{**k, "file": shown, "mininterval": 0})
    )
    result, _ = _fit(monkeypatch, 0.0, progress=True)
    assert f"loss={result.losses[-2].item():.4g}" in shown.getvalue()

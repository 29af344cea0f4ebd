"""Every --lr is honoured or refused: entries that train at their recipe's own rate (ACT,
Diffusion Policy) refuse another one instead of ignoring it; no --lr means each
learner's own default, and checkpoints rebuild at the rate they trained with."""

from __future__ import annotations

import json

import pytest

from imitrl.envs import make_env
from imitrl.jobs.bc import run_bc
from imitrl.jobs.checkpoint import CONFIG_FILE, load_learner
from imitrl.jobs.configs import BCJob
from imitrl.jobs.resolve import learner_factory
from imitrl.learners import defaults as registry_defaults
from imitrl.learners import registry
from imitrl.learners.act.entries import ACT_LR
from imitrl.learners.diffusion_unet import DIFFUSION_UNET


def _rate(learner) -> float:
    return learner.opt_pi.param_groups[0]["lr"]


def test_entries_with_their_own_rate_refuse_another_and_take_theirs_by_default():
    env = make_env("Pendulum-v1", seed=0)
    assert registry.get("act").own_lr == ACT_LR
    assert registry.get("diffusion_unet").own_lr == DIFFUSION_UNET.lr
    for name, own in (("act", ACT_LR), ("diffusion_unet", DIFFUSION_UNET.lr)):
        with pytest.raises(ValueError, match=f"--loss {name} trains at its recipe's learning"):
            learner_factory(name, env, hidden=None, lr=own * 10, seed=0)
        with pytest.raises(ValueError, match=f"--loss {name} has no hidden layers"):
            learner_factory(name, env, hidden=(8,), lr=None, seed=0)  # its widths: its own
        for lr in (None, own):  # no --lr, or the recipe's own: built at the recipe's rate
            assert _rate(learner_factory(name, env, hidden=None, lr=lr, seed=0)()) == own


def test_every_other_entry_honours_lr_and_defaults_to_the_learner_config():
    env = make_env("Pendulum-v1", seed=0)
    for name in ("default", "mse", "gaussian_nll", "flow_chunk"):
        assert _rate(learner_factory(name, env, hidden=(8,), lr=0.02, seed=0)()) == 0.02
        assert (
            _rate(learner_factory(name, env, hidden=(8,), lr=None, seed=0)())
            == registry_defaults.NETWORK_LR
        )
    assert BCJob().lr is None  # the CLI's --lr: none = the loss's own


def test_a_checkpoint_rebuilds_without_a_recorded_rate_and_from_an_older_act_run(tmp_path):
    config = BCJob(env="Pendulum-v1", loss="act", demos=1, num_steps=2, eval_episodes=1,
                   out=tmp_path, progress=False)  # fmt: skip
    run_bc(config)
    saved = json.loads((tmp_path / CONFIG_FILE).read_text())
    assert saved["config"]["lr"] is None
    env = make_env("Pendulum-v1", seed=0)
    assert _rate(load_learner(tmp_path, env)) == ACT_LR
    saved["config"]["lr"] = (
        0.001  # what runs saved before act refused --lr (the default it ignored)
    )
    (tmp_path / CONFIG_FILE).write_text(json.dumps(saved))
    assert _rate(load_learner(tmp_path, env)) == ACT_LR
    saved["config"]["lr"] = "fast"
    (tmp_path / CONFIG_FILE).write_text(json.dumps(saved))
    with pytest.raises(ValueError, match="a positive number or null"):
        load_learner(tmp_path, env)

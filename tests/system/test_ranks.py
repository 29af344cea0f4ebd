"""Data-parallel fits on ``torch.distributed``: two gloo ranks at batch B end where one
process at batch 2B ends, parameter for parameter, for a state MLP, chunked and
generative losses and a pixel learner (issue 45); the rows are split as :func:`share`
says."""

from __future__ import annotations

import os

import pytest
import torch
import torch.multiprocessing as mp

from imitrl.system.ranks import rows_drawn, sharded, share
from tests import _child

B, STEPS = 16, 100
LOSSES = ("mse", "flow_chunk", "act", "diffusion_unet", "for_env")


def _rows(pixels: bool):
    from imitrl.envs import make_env
    from imitrl.experts import pendulum_expert
    from imitrl.runtime import rollout_episodes

    kw = {"pixels": (16, 16)} if pixels else {}
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=100, **kw)
    return env, rollout_episodes(env, pendulum_expert(), 2)


def fit(
    name: str, batch: int, disk: str | None = None, lerobot: str | None = None
) -> tuple[dict, torch.Tensor]:
    """Learner ``name`` fitted ``STEPS`` steps at ``batch`` rows (per rank): its policy's
    parameters and the logged losses. ``disk``: the rows in a disk buffer there;
    ``lerobot``: that LeRobot dataset (the same rows) streamed into it."""
    from imitrl.algorithms import BCConfig, fit_bc
    from imitrl.data import DemonstrationBuffer
    from imitrl.learners import build
    from imitrl.learners.diffusion_unet import UnetDiffusionConfig

    env, rows = _rows(pixels=name == "for_env")
    if disk is not None:
        buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched, path=disk)
        if lerobot is None:
            buffer.extend(rows)
        else:  # streamed, a piece at a time, into the disk buffer
            from imitrl.datasets import load_lerobot

            load_lerobot(lerobot, env=env, into=buffer)
        rows = buffer
    settings: dict = {"seed": 0}
    if name in ("mse", "flow_chunk"):
        settings["hidden"] = (16, 16)
    if name == "for_env":  # the camera network (Nature CNN) at a small width
        settings.update(state=False, head="deterministic", loss="mse", channels=(4,), hidden=(16,))
    if name == "diffusion_unet":  # the U-Net, narrow
        settings["options"] = UnetDiffusionConfig(down_dims=(8, 16), step_embed_dim=8, n_groups=4)
    learner = build(name, env, **settings)
    result = fit_bc(learner, rows, BCConfig(num_steps=STEPS, batch_size=batch, seed=0))
    params = {k: v.detach().clone() for k, v in learner.policy.state_dict().items()}
    return params, result.losses


def _rank(rank: int, world: int, init: str, out: str, lerobot: str | None) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init}", rank=rank, world_size=world)
    try:
        fits = {name: fit(name, B) for name in LOSSES}
        fits["disk"] = fit("mse", B, disk=f"{out}.rank{rank}")  # each rank's copy on disk
        if lerobot is not None:
            fits["lerobot"] = fit("mse", B, disk=f"{out}.lr{rank}", lerobot=lerobot)
        if rank == 0:
            torch.save(fits, out)
    finally:
        dist.destroy_process_group()


def _key_bias(name: str) -> bool:
    """An attention layer's bias of its keys: its gradient is zero in exact arithmetic
    (a softmax is blind to a constant added to every score), so Adam turns rounding noise
    into its steps, different in any other order of summation."""
    return name.endswith("in_proj_bias")


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ranks")
    out = str(folder / "fits.pt")
    lerobot = None
    try:
        from imitrl.datasets import save_lerobot

        lerobot = str(save_lerobot(_rows(pixels=False)[1], folder / "lerobot", fps=20))
    except ImportError:  # pyarrow, the datasets extra: that case is skipped
        pass
    mp.start_processes(
        _rank,
        args=(2, str(folder / "init"), out, lerobot),
        nprocs=2,
        join=True,
        start_method=_child.forkserver(),
    )
    return {**torch.load(out), "_lr": lerobot}


@pytest.mark.parametrize("name", [*LOSSES, "disk", "lerobot"])
def test_two_ranks_at_batch_b_are_one_process_at_2b(two_ranks, name, tmp_path):
    if name not in two_ranks:
        pytest.skip("the LeRobot case needs pyarrow (the datasets extra)")
    params, losses = two_ranks[name]
    if name == "disk":  # a disk buffer's own order (a lazy permutation), in one process
        one, one_losses = fit("mse", 2 * B, disk=str(tmp_path / "one"))
    elif name == "lerobot":  # streamed into a disk buffer, in one process
        one, one_losses = fit("mse", 2 * B, disk=str(tmp_path / "one"), lerobot=two_ranks["_lr"])
    else:
        one, one_losses = fit(name, 2 * B)
    assert torch.allclose(losses, one_losses, rtol=1e-5, atol=1e-6)  # the global batch's loss
    got_all, want_all = [], []
    for key, want in one.items():
        if not want.is_floating_point():
            continue
        got = params[key]
        if _key_bias(key):  # the query and value thirds are held to the rule
            d = want.shape[0] // 3
            got, want = torch.cat([got[:d], got[2 * d :]]), torch.cat([want[:d], want[2 * d :]])
        got_all.append(got.reshape(-1))
        want_all.append(want.reshape(-1))
        rel = ((got - want).norm() / want.norm().clamp_min(1e-12)).item()
        # ACT: Adam's steps on the keys' biases (rounding noise, _key_bias) reach the
        # other parameters of its attention through the float arithmetic, a little
        assert rel <= (1e-4 if name == "act" else 1e-6), (name, key, rel)
    got, want = torch.cat(got_all), torch.cat(want_all)
    assert ((got - want).norm() / want.norm()).item() <= 1e-6, name  # the whole vector


def test_share_splits_rows_contiguously_and_draws_keep_the_global_batchs():
    assert [share(10, r, 3) for r in range(3)] == [(0, 4), (4, 3), (7, 3)]
    assert [share(4, r, 2) for r in range(2)] == [(0, 2), (2, 2)]
    g = torch.Generator().manual_seed(0)
    whole = torch.randn(8, 2, generator=torch.Generator().manual_seed(0))
    with sharded(4, 8):
        part = rows_drawn(lambda m: torch.randn(m, 2, generator=g), 4)
    assert torch.equal(part, whole[4:])
    assert os.environ.get("RANK") is None  # a test process is no rank

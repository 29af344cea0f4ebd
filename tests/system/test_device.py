"""One device setting, end to end (issue 28): the learner where ``device=`` puts it, envs
and experts on the CPU, checkpoints that load on any device, clear errors.

Every test runs on each available device: the CPU always, CUDA where the machine has
it (CPU-only CI runs the CPU half; a GPU machine runs both). On the CPU, ``device="cpu"``
must give the digits of no ``device=`` at all, to the bit.
"""

from __future__ import annotations

import io
import json

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.data.chunks import add_chunk_labels
from imitrl.envs import make_env
from imitrl.envs.pixel_tasks import PixelBalanceEnv, balance_expert
from imitrl.evaluation import evaluate
from imitrl.experts import cartpole_expert, pendulum_expert
from imitrl.learners import TaskSpec, build, registry
from imitrl.runtime import rollout_episodes
from imitrl.system.device import OnDevice, acting, on_cpu, resolve_device
from tests.learners.test_registry import TASKS, _cases, _rows

DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]


# ----------------------------------------------------------------- naming a device
def test_device_names_resolve_and_bad_ones_are_named():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    auto = resolve_device("auto")
    assert auto.type == ("cuda" if torch.cuda.is_available() else "cpu")
    for bad in ("gpu", "cuda:x", "cpu:1", "", 3):
        with pytest.raises(ValueError, match="auto, cpu, cuda or cuda:N"):
            resolve_device(bad)
    if not torch.cuda.is_available():
        for asked in ("cuda", "cuda:0", "cuda:3"):
            with pytest.raises(ValueError, match=rf"device '{asked}' asked for, but this machine"):
                resolve_device(asked)
    else:
        with pytest.raises(ValueError, match="cuda:99"):
            resolve_device("cuda:99")


def test_every_command_refuses_a_device_it_cannot_use_in_one_line(capsys):
    from imitrl.cli import main

    assert main(["bc", "--device", "tpu"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--device: unknown device 'tpu'" in err


# ------------------------------------------------------------- fits on the device
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(("name", "tname"), list(_cases()))
def test_every_registry_loss_fits_on_the_device(name, tname, device):
    task = TASKS[tname]
    config = dict(hidden=(16, 16), lr=1e-2, seed=0, device=device)
    learner = build(name, task, shared=config)
    assert learner.device.type == device
    horizon = registry.get(name).horizon
    rows = _rows(task) if horizon is None else add_chunk_labels(_rows(task), horizon)
    result = fit_bc(learner, rows, BCConfig(num_steps=5, batch_size=16, seed=0))  # rows on CPU
    assert torch.isfinite(result.losses).all()
    if device == "cpu":  # the same digits as a learner built without device=
        plain = build(name, task, shared=dict(hidden=(16, 16), lr=1e-2, seed=0))
        again = fit_bc(plain, rows, BCConfig(num_steps=5, batch_size=16, seed=0))
        assert torch.equal(result.losses, again.losses)


@pytest.mark.parametrize("device", DEVICES)
def test_a_pixel_learner_fits_and_acts_on_the_device(device):
    env = PixelBalanceEnv(pixels=(16, 16), batch_size=(2,), seed=0)
    rows = rollout_episodes(env, balance_expert(), 2)
    learner = build("for_env", env, channels=(4,), hidden=(16,), seed=0, device=device)
    fit_bc(learner, rows, BCConfig(num_steps=3, batch_size=32))  # CPU rows, batches moved
    ev = evaluate(env, learner, 2, seed=1)  # CPU env, the policy on the device
    assert ev.num_episodes == 2 and ev.mean_return == ev.mean_return  # played, finite


@pytest.mark.parametrize("device", DEVICES)
def test_a_dagger_round_and_evaluate_with_the_learner_on_the_device(device):
    env = make_env("CartPole-v1", seed=0, max_episode_steps=30)
    expert = cartpole_expert()
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, expert, 1))

    def make():
        return build("for_env", env, hidden=(16,), seed=0, device=device)

    config = DAggerConfig(rounds=2, episodes_per_round=1, bc=BCConfig(num_steps=10, batch_size=16))
    result = dagger(EnvSource(env), expert, make, buffer, config)
    assert result.learner.device.type == device
    assert set(buffer.rounds()) == {0, 1}
    assert buffer.data.device in (None, torch.device("cpu"))  # rows stay on the CPU
    ev = evaluate(env, result.learner, 3, seed=5)
    assert ev.num_episodes == 3 and 1 <= ev.mean_length <= 30
    if device == "cpu":  # a CPU learner is not wrapped: same calls, same digits
        assert acting(result.learner.policy, "cpu") is result.learner.policy
        assert not result.learner.opt_pi.param_groups[0]["fused"]
    else:  # on a GPU the device's own fused Adam takes each step
        assert result.learner.opt_pi.param_groups[0]["fused"]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("algorithm", ["gail", "airl"])
def test_gail_and_airl_steps_with_the_learner_on_the_device(device, algorithm):
    from imitrl.algorithms.adversarial import AIRLConfig, GAILConfig, airl, gail

    env = make_env("Pendulum-v1", seed=0, max_episode_steps=20)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, pendulum_expert(), 2))
    learner = build(
        "for_env", env, head="tanh_normal", hidden=(16,), seed=0, device=device, value=True
    )
    small = dict(total_steps=64, rollout_steps=32, ppo_epochs=1, minibatch_size=16,
                 discriminator_updates=1, discriminator_batch=16, normalizer_warmup=0)  # fmt: skip
    if algorithm == "gail":
        result = gail(env, learner, buffer, GAILConfig(**small))
    else:
        result, _ = airl(env, learner, buffer, AIRLConfig(**small))
    assert result.env_steps == 64 and learner.device.type == device


# ------------------------------------------------------- crossing the device once
def test_a_tensordict_without_a_device_is_on_the_cpu_when_its_leaves_are():
    # what fit_bc's batches and the rollout's values are: TensorDict(...) without device=
    rows = TensorDict({"a": torch.zeros(2), ("n", "b"): torch.ones(2, 3)}, batch_size=[2])
    assert rows.device is None and on_cpu(rows)  # the crash on CUDA read rows.device.type
    assert on_cpu(rows.to("cpu")) and on_cpu(torch.zeros(1))
    assert not on_cpu(TensorDict({"a": torch.zeros(2, device="meta")}, batch_size=[2]))
    assert not on_cpu(TensorDict({}, batch_size=[2]))  # no leaf says where it is
    assert not on_cpu(torch.zeros(1, device="meta"))


def test_a_policy_holding_a_wrapped_learner_acts_as_it_is():
    # DAgger's behaviour policy: the learner already crosses through OnDevice, the CPU
    # expert beside it must read the env's tensors where they are (found on a GPU)
    from tensordict.nn import TensorDictModule, TensorDictSequential

    far = TensorDictModule(torch.nn.Linear(4, 2, device="meta"), ["observation"], ["action"])
    wrapped = acting(far, "cpu")
    assert isinstance(wrapped, OnDevice) and wrapped.device.type == "meta"
    expert = TensorDictModule(lambda obs: obs * 2, ["observation"], ["expert_action"])
    behaviour = TensorDictSequential(wrapped, expert)
    assert acting(behaviour, "cpu") is behaviour  # not wrapped again around the expert
    assert acting(wrapped, "cpu") is wrapped
    assert acting(expert, "cpu") is expert  # no parameters: a CPU function, as before
    near = TensorDictModule(torch.nn.Linear(4, 2), ["observation"], ["action"])
    assert acting(TensorDictSequential(wrapped, near), "cpu").__class__ is TensorDictSequential


def test_on_device_reads_its_keys_there_and_writes_its_outputs_back():
    policy = build("for_env", TaskSpec.from_specs(3, 2), hidden=(8,), seed=0).policy
    wrapped = OnDevice(policy, torch.device("cpu"))
    td = TensorDict({keys.OBSERVATION: torch.randn(4, 3), "other": torch.zeros(4)}, [4])
    out = wrapped(td.clone())
    assert torch.equal(out[keys.ACTION], policy(td.clone())[keys.ACTION])
    assert torch.equal(out["other"], td["other"])  # what it does not write is left alone


# --------------------------------------------------- checkpoints on any device
def _as_if_saved_on_cuda(obj, save=torch.save) -> bytes:
    """``torch.save(obj)`` with every storage recorded as ``cuda:0`` (what a GPU run
    writes), made on a CPU-only machine: torch records each storage's device through
    ``torch.serialization.location_tag``."""
    import torch.serialization as ser

    real = ser.location_tag
    ser.location_tag = lambda storage: "cuda:0"
    try:
        buf = io.BytesIO()
        save(obj, buf)
    finally:
        ser.location_tag = real
    return buf.getvalue()


def test_a_checkpoint_saved_on_a_gpu_loads_on_this_machine(tmp_path):
    from imitrl.jobs.checkpoint import load_learner

    env = make_env("CartPole-v1", seed=0)
    learner = build("for_env", env, hidden=(8,), seed=3)
    learner.prepare(rollout_episodes(env, cartpole_expert(), 1))
    raw = _as_if_saved_on_cuda(learner.state_dict())
    if not torch.cuda.is_available():  # what a plain torch.load of it does here
        with pytest.raises(RuntimeError, match="CUDA"):
            torch.load(io.BytesIO(raw), weights_only=True)
    ckpt = tmp_path / "run"
    ckpt.mkdir()
    (ckpt / "learner.pt").write_bytes(raw)
    config = {"env": "CartPole-v1", "loss": "default", "hidden": [8], "lr": 1e-3, "seed": 0,
              "max_episode_steps": None}  # fmt: skip
    (ckpt / "config.json").write_text(json.dumps({"command": "bc", "config": config}))
    for device in DEVICES:
        loaded = load_learner(ckpt, env, device=device)
        assert loaded.device.type == device
        for k, v in learner.state_dict().items():
            assert torch.equal(loaded.state_dict()[k].cpu(), v), k


def test_a_buffer_checkpoint_with_a_gpu_learner_loads_its_weights_on_the_cpu(tmp_path):
    from imitrl.data import checkpoint as ckpt

    env = make_env("CartPole-v1", seed=0)
    learner = build("for_env", env, hidden=(8,), seed=3)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, cartpole_expert(), 1))
    fit_bc(learner, buffer, BCConfig(num_steps=3, batch_size=8))  # optimizer state too
    real = torch.save

    def save_as_gpu(obj, f, *args, **kwargs):
        f.write(_as_if_saved_on_cuda(obj, save=real))

    torch.save = save_as_gpu
    try:
        path = buffer.save(tmp_path / "ck", learner=learner)
    finally:
        torch.save = real
    fresh = build("for_env", env, hidden=(8,), seed=99)
    DemonstrationBuffer.load(path, learner=fresh)
    for k, v in learner.state_dict().items():
        assert torch.equal(fresh.state_dict()[k], v), k
    assert set(ckpt.learner_components(fresh)) == {"learner", "opt_pi"}  # no value head


def test_weights_that_cannot_be_read_are_named_in_one_line(tmp_path):
    from imitrl.jobs.checkpoint import load_learner

    ckpt = tmp_path / "run"
    ckpt.mkdir()
    (ckpt / "learner.pt").write_bytes(b"not a torch archive")
    config = {"env": "CartPole-v1", "loss": "default", "hidden": [8], "lr": 1e-3, "seed": 0,
              "max_episode_steps": None}  # fmt: skip
    (ckpt / "config.json").write_text(json.dumps({"command": "bc", "config": config}))
    with pytest.raises(ValueError, match=r"learner.pt: not a learner's weights"):
        load_learner(ckpt, make_env("CartPole-v1", seed=0))


def test_the_evaluation_of_a_cpu_learner_is_unchanged_by_the_device_layer():
    env = make_env("CartPole-v1", seed=0, max_episode_steps=50)
    learner = build("for_env", env, hidden=(8,), seed=1)
    placed = build("for_env", env, hidden=(8,), seed=1, device="cpu")
    a = evaluate(env, learner, 4, seed=3, exploration=ExplorationType.RANDOM)
    b = evaluate(env, placed, 4, seed=3, exploration=ExplorationType.RANDOM)
    assert (a.mean_return, a.return_ci, a.mean_length) == (
        b.mean_return,
        b.return_ci,
        b.mean_length,
    )


# ------------------------------------------------------ a fit's arithmetic options
def _mlp_rows(n: int = 128) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, 4, generator=g)
    return TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: obs[:, :1].tanh()}, [n])


@pytest.mark.parametrize("device", DEVICES)
def test_a_bf16_fit_keeps_float32_weights_and_learns_as_fp32_does(device):
    from torchrl.data import Bounded

    spec = Bounded(-1.0, 1.0, shape=(1,))
    runs = {}
    for precision in ("fp32", "bf16"):
        learner = build(
            "for_env", TaskSpec.from_specs(4, spec), hidden=(32,), seed=0, device=device
        )
        config = BCConfig(num_steps=150, batch_size=32, seed=0, precision=precision)
        runs[precision] = fit_bc(learner, _mlp_rows(), config)
        assert all(p.dtype == torch.float32 for p in learner.parameters())
    fp32, bf16 = runs["fp32"].losses, runs["bf16"].losses
    assert not torch.equal(fp32, bf16)  # bfloat16 did change the arithmetic
    assert bf16[-20:].mean() < 0.5 * bf16[:20].mean()  # and it learns
    assert abs(bf16[-20:].mean() - fp32[-20:].mean()) < 0.1 * fp32[:20].mean()
    with pytest.raises(ValueError, match="precision must be one of"):
        BCConfig(precision="fp16")


def test_a_compiled_fit_gives_the_eager_fits_losses():
    from torchrl.data import Bounded

    spec = Bounded(-1.0, 1.0, shape=(1,))
    out = []
    for compile_ in (False, True):
        learner = build("for_env", TaskSpec.from_specs(4, spec), hidden=(16,), seed=0)
        config = BCConfig(num_steps=20, batch_size=32, seed=0, compile=compile_)
        out.append(fit_bc(learner, _mlp_rows(), config).losses)
    torch.testing.assert_close(out[1], out[0], rtol=1e-4, atol=1e-6)

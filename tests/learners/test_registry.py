"""The loss registry and its loss modules: contracts, exact values, one learning check."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.algorithms.policy_step import policy_step
from imitrl.data import DemonstrationBuffer
from imitrl.data.chunks import EXPERT_CHUNK, IS_INIT
from imitrl.envs import TabularEnv
from imitrl.learners import ActorCritic, Learner, TaskSpec, build, registry
from imitrl.learners.diffusion import DiffusionBehaviorCloningLoss, DiffusionPolicy
from imitrl.objectives import AdvantageWeightedLoss, BehaviorCloningLoss, RegularizedBCLoss
from imitrl.policies import Expert
from imitrl.runtime import rollout_episodes

SPEC = Bounded(-2.0, 2.0, shape=(1,))
TASKS = {
    "discrete_vector": TaskSpec(action=3, observation_dim=4),
    "discrete_table": TaskSpec(action=4, num_states=6, advantage=lambda s, a: (s + a).float() / 10),
    "continuous": TaskSpec(action=SPEC, observation_dim=3),
}


def _rows(task: TaskSpec, n: int = 64, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    if task.num_states is not None:
        obs = torch.randint(task.num_states, (n,), generator=g)
    else:
        obs = torch.randn(n, task.observation_dim, generator=g)
    if task.actions == "discrete":
        label = torch.randint(task.action, (n,), generator=g)
    else:
        label = torch.rand(n, 1, generator=g) * 4 - 2
    # four episodes of n / 4 steps (what chunk labels are formed from)
    episode, step = torch.arange(n) // (n // 4), torch.arange(n) % (n // 4)
    return TensorDict(
        {keys.OBSERVATION: obs, keys.EXPERT_ACTION: label, keys.EPISODE: episode, keys.STEP: step},
        [n],
    )


def _cases():
    for entry in registry.entries():
        for tname, task in TASKS.items():
            if entry.applies_to(task):
                yield pytest.param(entry.name, tname, id=f"{entry.name}-{tname}")


CONFIG = dict(hidden=(16, 16), lr=1e-2, seed=0)


@pytest.mark.parametrize(("name", "tname"), list(_cases()))
def test_every_entry_builds_acts_and_trains(name, tname):
    task = TASKS[tname]
    learner = build(name, task, shared=CONFIG)
    assert isinstance(learner, Learner)
    horizon = registry.get(name).horizon
    assert learner.horizon == horizon and learner.history == registry.get(name).history
    rows = learner.training_rows(_rows(task))  # chunk labels and histories, where it needs them
    # acts: one action per row, of the action space's dtype, inside the bounds (a chunked
    # learner: the first action of a fresh plan)
    inputs = rows.select(keys.OBSERVATION).clone()
    inputs.set(IS_INIT, torch.ones(rows.shape[0], 1, dtype=torch.bool))
    with torch.no_grad(), set_exploration_type(learner.exploration):
        action = learner.policy(inputs).get(keys.ACTION)
    assert action.shape == rows[keys.EXPERT_ACTION].shape
    if task.actions == "discrete":
        assert not action.dtype.is_floating_point
        assert ((action >= 0) & (action < task.action)).all()
    else:
        assert action.dtype == torch.float32
        assert ((action >= -2) & (action <= 2)).all()
    # the loss reads the label key, returns scalar loss_* entries with gradients
    assert (keys.EXPERT_ACTION if horizon is None else EXPERT_CHUNK) in learner.loss.in_keys
    out = learner.loss(rows)
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    assert total.ndim == 0 and total.requires_grad
    # trains through fit_bc: the loss goes down on a fixed batch
    result = fit_bc(learner, rows, BCConfig(num_steps=60, seed=0))
    assert result.losses[-10:].mean() < result.losses[:10].mean()


def test_entries_that_do_not_apply_are_refused_with_the_reason():
    with pytest.raises(ValueError, match="continuous"):
        build("mse", TASKS["discrete_vector"])
    with pytest.raises(ValueError, match="advantage"):
        build("advantage_weighted", TASKS["discrete_vector"])
    with pytest.raises(ValueError, match="unknown loss 'nope'"):
        build("nope", TASKS["continuous"])
    assert "advantage_weighted" not in registry.names(TASKS["discrete_vector"])
    assert "advantage_weighted" in registry.names(TASKS["discrete_table"])
    assert set(registry.names(TASKS["continuous"])) >= {
        "gaussian_nll",
        "mse",
        "l1",
        "smooth_l1",
        "diffusion",
    }


def test_register_rejects_duplicates_and_unknown_requirements():
    with pytest.raises(ValueError, match="already registered"):
        registry.register("mse", actions="continuous", summary="again")(lambda t, c: None)
    with pytest.raises(ValueError, match="actions"):
        registry.register("x", actions="both", summary="")
    with pytest.raises(ValueError, match="unknown TaskSpec fields"):
        registry.register("x", actions="discrete", summary="", requires=("q_table",))
    with pytest.raises(ValueError, match="batch_size must be a positive integer"):
        registry.register("x", actions="continuous", summary="", batch_size=0)
    assert registry.get("act").batch_size is not None and registry.get("mse").batch_size is None

    @registry.register("test_bad_return", actions="discrete", summary="returns the wrong type")
    def _(task, config):
        return build(
            "cross_entropy", TaskSpec(action=2, num_states=2)
        ).policy  # a policy module, not a Learner

    try:
        with pytest.raises(ValueError, match="expected a Learner"):
            build("test_bad_return", TaskSpec(action=2, num_states=2))
    finally:
        registry.unregister("test_bad_return")
    assert "test_bad_return" not in registry.names()
    with pytest.raises(ValueError, match="exactly one"):
        TaskSpec(action=2, num_states=3, observation_dim=2)


# ------------------------------------------------------------------ exact values
def test_advantage_weighted_loss_is_policy_steps_objective():
    ac = build("cross_entropy", TaskSpec(action=4, num_states=6))
    with torch.no_grad():
        ac.policy.module[0].module.weight.copy_(
            torch.randn(6, 4, generator=torch.Generator().manual_seed(1))
        )
    rows = _rows(TASKS["discrete_table"], n=32)
    adv = TASKS["discrete_table"].advantage
    loss = AdvantageWeightedLoss(ac.policy, adv)(rows)
    weights = adv(rows[keys.OBSERVATION], rows[keys.EXPERT_ACTION])
    before = policy_step(ac, rows, weights, action_key=keys.EXPERT_ACTION)  # loss before its step
    assert loss["loss_bc"].item() == pytest.approx(before, abs=1e-6)
    logits = torch.randn(6, 4, generator=torch.Generator().manual_seed(1))
    ref = (
        weights
        * F.cross_entropy(
            logits[rows[keys.OBSERVATION]], rows[keys.EXPERT_ACTION], reduction="none"
        )
    ).mean()
    assert loss["loss_bc"].item() == pytest.approx(ref.item(), abs=1e-6)
    with pytest.raises(ValueError, match="one weight per row"):
        AdvantageWeightedLoss(ac.policy, lambda s, a: torch.ones(3))(rows)


def test_regularized_loss_terms_are_exact():
    ac = build("for_env", TaskSpec.from_specs(4, 3), hidden=(8,), seed=0)
    rows = _rows(TASKS["discrete_vector"])
    plain = BehaviorCloningLoss(ac.policy, loss_type="nll")(rows)["loss_bc"]
    none = RegularizedBCLoss(ac.policy, loss_type="nll")(rows)
    assert set(k for k in none.keys() if k.startswith("loss_")) == {"loss_bc"}
    assert torch.allclose(none["loss_bc"], plain)
    out = RegularizedBCLoss(ac.policy, loss_type="nll", entropy_coef=0.1, l2_coef=0.01)(rows)
    logits = ac.policy.module[0](rows.select(keys.OBSERVATION).clone())[keys.LOGITS]
    entropy = torch.distributions.Categorical(logits=logits).entropy().mean()
    l2 = sum(p.pow(2).sum() for n, p in ac.policy.named_parameters() if n.endswith("weight"))
    assert torch.allclose(out["loss_entropy"], -0.1 * entropy, atol=1e-6)
    assert torch.allclose(out["loss_l2"], 0.01 * l2, atol=1e-6)
    with pytest.raises(ValueError, match="probabilistic"):
        det = build("for_env", TaskSpec.from_specs(3, SPEC), head="deterministic", hidden=(8,))
        RegularizedBCLoss(det.policy, loss_type="mse", entropy_coef=0.1)


def test_diffusion_policy_maps_bounds_and_is_reproducible():
    policy = DiffusionPolicy(3, SPEC, hidden=(16,), num_steps=5, seed=0)
    assert torch.equal(
        policy.normalize(torch.tensor([[-2.0], [0.0], [2.0]])), torch.tensor([[-1.0], [0.0], [1.0]])
    )
    obs = TensorDict({keys.OBSERVATION: torch.randn(50, 3)}, [50])

    def sample(p):
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            return p(obs.clone())[keys.ACTION]

    twin = DiffusionPolicy(3, SPEC, hidden=(16,), num_steps=5, seed=0)
    torch.manual_seed(123)  # the global RNG does not matter
    a = sample(policy)
    torch.manual_seed(456)
    assert torch.equal(a, sample(twin))
    assert a.shape == (50, 1) and ((a >= -2) & (a <= 2)).all()
    assert not torch.equal(a, sample(policy))  # the policy's own stream moved on
    rows = _rows(TASKS["continuous"])
    l1 = DiffusionBehaviorCloningLoss(policy, seed=3)(rows)["loss_diffusion_bc"]
    l2 = DiffusionBehaviorCloningLoss(twin, seed=3)(rows)["loss_diffusion_bc"]
    assert torch.equal(l1, l2)
    with pytest.raises(ValueError, match="float"):
        DiffusionBehaviorCloningLoss(policy)(
            rows.set(keys.EXPERT_ACTION, torch.zeros(64, 1, dtype=torch.int64))
        )


# ----------------------------------------------------------- fit_bc / dagger hooks
def test_a_learner_given_its_default_loss_explicitly_fits_identically():
    rows = _rows(TASKS["discrete_vector"], n=128)
    cfg = BCConfig(num_steps=30, batch_size=32, seed=4)
    a = build("for_env", TaskSpec.from_specs(4, 3), seed=0)
    policy_b = build("for_env", TaskSpec.from_specs(4, 3), seed=0)
    b = ActorCritic(
        policy_b.policy,
        policy_b.value,
        head="categorical",
        loss=BehaviorCloningLoss(policy_b.policy, loss_type="nll"),
        lr=policy_b.lr,
        observation_shape=(4,),
        normalizer=policy_b.normalizer,
    )
    assert torch.equal(fit_bc(a, rows, cfg).losses, fit_bc(b, rows, cfg).losses)
    loss = BehaviorCloningLoss(b.policy, loss_type="nll")
    loss.set_keys(label="other")
    with pytest.raises(ValueError, match=r"rows lack \['other'\]"):
        fit_bc(Learner(b.policy, loss, b.opt_pi), rows, cfg)
    with pytest.raises(ValueError, match="SummedLoss"):
        Learner(b.policy, torch.nn.MSELoss(), b.opt_pi)


def test_dagger_trains_registry_learners_through_the_fit_hook(lake, expert_table):
    env = TabularEnv(lake, batch_size=(3,), seed=0)
    buffer = DemonstrationBuffer(num_states=16)
    expert = Expert.from_table(expert_table)
    buffer.extend(
        rollout_episodes(
            env, expert.as_actor(), 1, exploration=ExplorationType.DETERMINISTIC, max_steps=10_000
        )
    )
    task = TaskSpec(action=4, num_states=16)
    fitted = []
    cfg = BCConfig(num_steps=50)

    def train(learner, buf):
        fitted.append(len(buf))
        return fit_bc(learner, buf, cfg)

    result = dagger(
        EnvSource(env),
        expert,
        lambda: build("cross_entropy_entropy", task, shared=dict(lr=0.1)),
        buffer,
        DAggerConfig(rounds=3, episodes_per_round=3),
        train=train,
    )
    assert fitted == [r.rows_trained for r in result.rounds]
    assert fitted[0] < fitted[1] < fitted[2]
    assert isinstance(result.learner, Learner)


@pytest.mark.slow  # benchmarks/loss_functions.py measures the modes of every loss
# ------------------------------------------------------------------------ learning
def test_diffusion_keeps_both_modes_where_mse_averages_them():
    # one observation dimension, labels +-0.5 with equal probability everywhere
    g = torch.Generator().manual_seed(0)
    n = 1024
    obs = torch.rand(n, 1, generator=g)
    label = torch.where(torch.rand(n, 1, generator=g) < 0.5, 0.5, -0.5)
    rows = TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, [n])
    task = TaskSpec(action=Bounded(-1.0, 1.0, shape=(1,)), observation_dim=1)
    cfg = dict(hidden=(32, 32), lr=1e-2, seed=0)
    fit = BCConfig(num_steps=1200, batch_size=256, seed=0)
    test_obs = TensorDict({keys.OBSERVATION: torch.rand(2000, 1, generator=g)}, [2000])
    fractions = {}
    for name in ("mse", "diffusion"):
        learner = build(name, task, shared=cfg)
        fit_bc(learner, rows, fit)
        with torch.no_grad(), set_exploration_type(learner.exploration):
            a = learner.policy(test_obs.clone())[keys.ACTION]
        fractions[name] = (
            ((a - 0.5).abs() < 0.25).float().mean(),
            ((a + 0.5).abs() < 0.25).float().mean(),
        )
    # MSE: nothing near either mode; diffusion: each mode 30-70% of 2000 samples
    assert max(fractions["mse"]) == 0
    assert all(0.3 < f < 0.7 for f in fractions["diffusion"]), fractions


def test_a_pixel_learner_given_another_loss_keeps_its_pixel_inputs_and_action_space():
    # registry._with_loss used to rebuild the ActorCritic without pixel_inputs / action
    from imitrl.envs.pixel_tasks import PixelTwoWayEnv
    from imitrl.learners.actor_critic.entries import _with_loss

    spec = Bounded(-1.0, 1.0, shape=(1,))
    ac = ActorCritic.pixels((16, 16, 3), spec, channels=(8, 8), hidden=(32,))
    swapped = _with_loss(ac, RegularizedBCLoss(ac.policy, loss_type="mse", l2_coef=1e-4))
    assert swapped.pixel_inputs is ac.pixel_inputs and swapped.pixel_key == keys.PIXELS
    assert swapped.action_space is ac.action_space
    swapped.check_env(PixelTwoWayEnv(pixels=(16, 16), seed=0))  # reads the images: no error
    images = torch.zeros(4, 16, 16, 3, dtype=torch.uint8)
    assert swapped.act_greedy({keys.PIXELS: images}).shape == (4, 1)


def test_an_entry_whose_learner_has_another_horizon_is_refused_when_built():
    """A hostile review: an entry registered with horizon 4 that built a one-step learner
    was taken; the CLI chunks labels by the entry's horizon, the learner by its own."""

    @registry.register("test_horizon_4", actions="continuous", summary="not chunked", horizon=4)
    def _(task, config):
        return build("mse", task)

    try:
        with pytest.raises(ValueError, match="registered with horizon 4 but built a learner of"):
            build("test_horizon_4", TASKS["continuous"])
    finally:
        registry.unregister("test_horizon_4")


def test_an_entrys_options_may_set_another_chunk_length():
    """``build("diffusion_unet", env, horizon=4, action_steps=3)`` (the Meta-World
    horizons of the published Diffusion Policy numbers) was refused as a horizon other
    than the entry's 16; a chunk length is one of the entry's options, and the fit forms
    chunk labels of the learner's own length."""
    learner = build("diffusion_unet", TASKS["continuous"], horizon=4, action_steps=3)
    assert learner.horizon == 4 and registry.get("diffusion_unet").horizon == 16
    rows = learner.training_rows(_rows(TASKS["continuous"]))
    assert rows.get(EXPERT_CHUNK).shape == (64, 4, 1)  # chunks of the learner's length
    losses = fit_bc(learner, rows, BCConfig(num_steps=3, batch_size=16, seed=0)).losses
    assert losses.shape == (3,) and bool(torch.isfinite(losses).all())
    inputs = rows.select(keys.OBSERVATION)[:2].clone()
    inputs.set(IS_INIT, torch.ones(2, 1, dtype=torch.bool))
    with torch.no_grad(), set_exploration_type(learner.exploration):
        assert learner.policy(inputs).get(keys.ACTION).shape == (2, 1)


def test_options_never_make_a_chunked_entry_build_a_one_step_learner():
    """Options may change a chunk's length, not whether the learner predicts chunks."""

    @registry.register(
        "test_opts_h4", actions="continuous", summary="x", horizon=4, options=UnetDefaults()
    )
    def _(task, config):
        return build("mse", task)

    try:
        with pytest.raises(ValueError, match="registered with horizon 4 but built a learner of"):
            build("test_opts_h4", TASKS["continuous"], width=3)
    finally:
        registry.unregister("test_opts_h4")


@dataclass(frozen=True)
class UnetDefaults:
    width: int = 2

"""GAIL and AIRL: exact reward formulas, discriminator contracts, learning on CartPole,
reproducibility, and the ``imitrl gail`` / ``imitrl airl`` jobs."""

from __future__ import annotations

import json
import math
import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms.adversarial import (
    AIRLConfig,
    AIRLDiscriminator,
    GAILConfig,
    GAILDiscriminator,
    airl,
    airl_reward,
    gail,
    gail_reward,
    shaped_f,
)
from imitrl.algorithms.adversarial.keys import (
    ABSORBING,
    ACTION_FEATURES,
    EXPERT_PROBABILITY,
    POLICY,
    STATE_FEATURES,
)
from imitrl.algorithms.adversarial.transitions import expert_transitions
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.experts import cartpole_expert
from imitrl.jobs.checkpoint import load_learner
from imitrl.jobs.curves import read_scalars, scalars_dir
from imitrl.jobs.gail import AIRLJob, GAILJob, run_airl, run_gail
from imitrl.learners import ActorCritic, TaskSpec, build
from imitrl.runtime import rollout_episodes
from imitrl.runtime.returns import episode_returns

GREEDY = ExplorationType.DETERMINISTIC
NEXT_OBS, NEXT_TERM = (keys.NEXT, keys.OBSERVATION), (keys.NEXT, keys.TERMINATED)


# ------------------------------------------------------------------ helpers
def _transitions(obs, action, next_obs=None, terminated=None) -> TensorDict:
    n = obs.shape[0]
    return TensorDict(
        {
            keys.OBSERVATION: obs,
            keys.ACTION: action,
            NEXT_OBS: obs + 0.1 if next_obs is None else next_obs,
            NEXT_TERM: torch.zeros(n, 1, dtype=torch.bool) if terminated is None else terminated,
            ABSORBING: torch.zeros(n, 1, dtype=torch.bool),
            (keys.NEXT, ABSORBING): torch.zeros(n, 1, dtype=torch.bool),
        },
        batch_size=[n],
    )


def _separable(n: int = 64, seed: int = 0) -> tuple[TensorDict, TensorDict]:
    """Expert: observations around +1, action 1; policy: around -1, action 0."""
    g = torch.Generator().manual_seed(seed)
    expert = _transitions(1 + 0.3 * torch.randn(n, 2, generator=g), torch.ones(n, dtype=torch.long))
    policy = _transitions(
        -1 + 0.3 * torch.randn(n, 2, generator=g), torch.zeros(n, dtype=torch.long)
    )
    return expert, policy


def _learner() -> ActorCritic:
    return build(
        "for_env", TaskSpec.from_specs(2, 2), hidden=(16,), normalize=False, seed=0, value=True
    )


def _mann_whitney_p(after: torch.Tensor, before: torch.Tensor) -> float:
    """One-sided p-value of Mann-Whitney U (after > before), normal approximation with the
    tie correction."""
    x = torch.cat([after, before]).double()
    n1, n2, n = after.numel(), before.numel(), x.numel()
    order = x.argsort()
    ranks = torch.empty(n, dtype=torch.float64)
    ranks[order] = torch.arange(1, n + 1, dtype=torch.float64)
    values, inverse, counts = torch.unique(x, return_inverse=True, return_counts=True)
    ranks = torch.zeros(values.numel(), dtype=torch.float64).index_add_(0, inverse, ranks)[inverse]
    ranks = ranks / counts[inverse]  # average rank of ties
    u = float(ranks[:n1].sum()) - n1 * (n1 + 1) / 2
    ties = float((counts.double() ** 3 - counts.double()).sum())
    sigma = math.sqrt(n1 * n2 / 12 * ((n + 1) - ties / (n * (n - 1))))
    z = (u - n1 * n2 / 2) / sigma
    return float(torch.special.ndtr(torch.tensor(-z, dtype=torch.float64)))


def _cartpole(seed: int):
    env = make_env("CartPole-v1", seed=seed)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, cartpole_expert(), 1))
    return env, buffer, build("for_env", env, lr=3e-4, seed=seed, value=True)


TINY = dict(total_steps=256, rollout_steps=128, ppo_epochs=2, minibatch_size=64,
            discriminator_updates=2, discriminator_batch=32)  # fmt: skip


# ------------------------------------------------------------- exact math
def test_gail_reward_is_minus_log_one_minus_d():
    logit = torch.tensor([-8.0, -2.0, 0.0, 1.5, 8.0], dtype=torch.float64)
    d = torch.sigmoid(logit)
    torch.testing.assert_close(gail_reward(logit), -torch.log(1 - d))
    assert torch.all(gail_reward(logit)[1:] > gail_reward(logit)[:-1])  # increasing in D
    far = gail_reward(torch.tensor([-100.0, 100.0]))  # 1 - D underflows; the reward does not
    assert torch.isfinite(far).all() and far[1] == 100.0


def test_airl_shaped_f_against_hand_computation():
    g = torch.tensor([[1.0], [2.0], [0.5]])
    h = torch.tensor([[0.2], [0.4], [-1.0]])
    h_next = torch.tensor([[3.0], [5.0], [7.0]])
    terminated = torch.tensor([[False], [True], [False]])
    f = shaped_f(g, h, h_next, terminated, gamma=0.9)
    # 1 + 0.9 * 3 - 0.2; terminal: 2 - 0.4 (h(s') zeroed); 0.5 + 0.9 * 7 + 1
    torch.testing.assert_close(f, torch.tensor([[3.5], [1.6], [7.8]]))
    torch.testing.assert_close(shaped_f(g, h, h_next, terminated, gamma=0.0), g - h)


def test_airl_reward_is_log_d_minus_log_one_minus_d():
    f = torch.tensor([[0.3], [-1.2], [2.0]], dtype=torch.float64)
    pi = torch.tensor([[0.5], [0.1], [0.9]], dtype=torch.float64)
    d = f.exp() / (f.exp() + pi)  # eq. 2 of Fu et al.
    torch.testing.assert_close(airl_reward(f, pi.log()), d.log() - (1 - d).log())


def test_airl_network_decomposition_shapes_gamma_and_terminal():
    learner = _learner()
    disc = AIRLDiscriminator(learner, gamma=0.9, hidden=(8,), seed=0)
    net = disc.network
    obs, next_obs = torch.randn(5, 3), torch.randn(5, 3)  # state features: d + 1 = 3
    term = torch.tensor([[False], [True], [False], [True], [False]])
    f, g, h, h_next = net(obs, next_obs, term)
    assert f.shape == g.shape == h.shape == h_next.shape == (5, 1)
    torch.testing.assert_close(f, g + 0.9 * (~term).float() * h_next - h)
    torch.testing.assert_close(net.g(obs), g)  # g reads s only: a state-only reward
    moved = next_obs + 10 * term.float()  # s' of terminal rows is never read
    f2 = net(obs, moved, term)[0]
    torch.testing.assert_close(f2[term.squeeze(-1)], f[term.squeeze(-1)])
    assert not torch.allclose(
        net(obs, next_obs + 1, term)[0][~term.squeeze(-1)], f[~term.squeeze(-1)]
    )


def test_airl_reward_matches_f_minus_log_pi_of_the_learner():
    learner = _learner()
    disc = AIRLDiscriminator(learner, gamma=0.99, hidden=(8,), seed=0)
    tr, _ = _separable(8)
    log_pi = learner.log_prob(tr[keys.OBSERVATION], tr[keys.ACTION]).detach().unsqueeze(-1)
    torch.testing.assert_close(disc.reward(tr), disc.f(tr).detach() - log_pi)


def test_airl_entropy_weight_scales_only_the_generator_s_log_pi():
    """``f - w log pi`` is the generator's reward; the discriminator's logit stays
    ``f - log pi`` (its loss does not depend on ``w``)."""
    learner = _learner()
    tr, _ = _separable(8)
    log_pi = learner.log_prob(tr[keys.OBSERVATION], tr[keys.ACTION]).detach().unsqueeze(-1)
    one = AIRLDiscriminator(learner, gamma=0.99, hidden=(8,), seed=0)
    zero = AIRLDiscriminator(learner, gamma=0.99, hidden=(8,), seed=0, entropy_weight=0.0)
    half = AIRLDiscriminator(learner, gamma=0.99, hidden=(8,), seed=0, entropy_weight=0.5)
    f = one.f(tr).detach()
    torch.testing.assert_close(zero.reward(tr), f)
    torch.testing.assert_close(half.reward(tr), f - 0.5 * log_pi)
    torch.testing.assert_close(zero.logits(tr), one.logits(tr))
    assert AIRLConfig(entropy_weight=0.0).entropy_weight == 0.0
    with pytest.raises(ValueError, match="entropy_weight"):
        AIRLConfig(entropy_weight=-1.0)
    job = AIRLJob(env="Pendulum-v1", expert="pendulum", entropy_weight=0.0)
    assert job.algorithm_config().entropy_weight == 0.0
    assert AIRLJob(env="Pendulum-v1", expert="pendulum").algorithm_config().entropy_weight == 1.0


# -------------------------------------------------------------- contracts
def test_gail_discriminator_keys_and_expert_side():
    disc = GAILDiscriminator(_learner(), hidden=(16,), seed=0)
    assert disc.module.in_keys == [STATE_FEATURES, ACTION_FEATURES]
    assert EXPERT_PROBABILITY in disc.module.out_keys
    assert (POLICY, STATE_FEATURES) in disc.loss.in_keys
    expert, policy = _separable()
    batch = disc.batch(expert, policy)
    assert batch[ACTION_FEATURES].shape == (64, 2)  # one-hot discrete actions
    assert batch[STATE_FEATURES].shape == (64, 3)  # observation and absorbing indicator
    with pytest.raises(ValueError, match="one to one"):
        disc.batch(expert, policy[:10])


def test_gail_reward_grows_on_expert_pairs_after_discriminator_steps():
    disc = GAILDiscriminator(_learner(), hidden=(16,), lr=1e-2, seed=0)
    expert, policy = _separable()
    before = disc.loss(disc.batch(expert, policy))["loss"].item()
    for _ in range(30):
        metrics = disc.update(expert, policy)
    # GAILLoss labels its expert_* side 1: D = P(expert), so -log(1 - D) rewards the expert
    assert disc.reward(expert).min() > disc.reward(policy).max()
    assert metrics["expert_accuracy"] == 1.0 and metrics["policy_accuracy"] == 1.0
    assert disc.loss(disc.batch(expert, policy))["loss"].item() < before


def test_gail_loss_gradients_reach_the_discriminator_only():
    learner = _learner()
    disc = GAILDiscriminator(learner, hidden=(16,), seed=0)
    expert, policy = _separable()
    disc.loss(disc.batch(expert, policy))["loss"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in disc.module.parameters())
    assert all(p.grad is None for p in learner.parameters())


def test_gail_gradient_penalty_changes_the_loss():
    expert, policy = _separable()
    plain = GAILDiscriminator(_learner(), hidden=(16,), seed=0)
    penalised = GAILDiscriminator(_learner(), hidden=(16,), grad_penalty=10.0, seed=0)
    torch.manual_seed(0)
    out = penalised.loss(penalised.batch(expert, policy))
    base = plain.loss(plain.batch(expert, policy))["loss"]
    assert out["gp_loss"] > 0
    torch.testing.assert_close(out["loss"], base + out["gp_loss"])


def test_airl_loss_gradients_spare_the_policy_and_penalty_adds():
    learner = _learner()
    expert, policy = _separable()
    disc = AIRLDiscriminator(learner, gamma=0.99, hidden=(8,), grad_penalty=10.0, seed=0)
    out = disc.loss(expert, policy)
    out["loss"].backward()
    assert all(p.grad is not None for p in disc.network.parameters())
    assert all(p.grad is None for p in learner.parameters())
    plain = AIRLDiscriminator(learner, gamma=0.99, hidden=(8,), seed=0)
    assert out["grad_penalty"] > 0
    torch.testing.assert_close(
        out["loss"].detach(), plain.loss(expert, policy)["loss"].detach() + out["grad_penalty"]
    )


def _two_episodes(obs: torch.Tensor, extra: dict | None = None) -> TensorDict:
    """Five expert rows of ``obs``: episode 0 (3 steps) terminates, episode 1 (2 steps)
    is cut by a time limit."""
    return TensorDict(
        {
            keys.OBSERVATION: obs,
            keys.ACTION: torch.zeros(5, dtype=torch.long),
            keys.EPISODE: torch.tensor([0, 0, 0, 1, 1]),
            keys.STEP: torch.tensor([0, 1, 2, 0, 1]),
            keys.EXPERT_EXECUTED: torch.ones(5, dtype=torch.bool),
            NEXT_TERM: torch.tensor([[False], [False], [True], [False], [False]]),
            **(extra or {}),
        },
        batch_size=[5],
    )


def test_expert_transitions_link_rows_and_drop_cut_episode_ends():
    obs = torch.arange(10.0).reshape(5, 2)
    rows = _two_episodes(obs)
    tr = expert_transitions(rows)  # episode 1 ends by truncation: its last row is dropped
    assert tr.shape == (4,)
    torch.testing.assert_close(tr[NEXT_OBS][:2], obs[1:3])
    torch.testing.assert_close(tr[NEXT_OBS][3], obs[4])
    assert tr[NEXT_TERM].squeeze(-1).tolist() == [False, False, True, False]
    rows[keys.EXPERT_EXECUTED][1] = False
    with pytest.raises(ValueError, match="expert's own trajectories"):
        expert_transitions(rows)


def test_configs_and_learners_are_checked():
    with pytest.raises(ValueError, match="rollout_steps"):
        GAILConfig(rollout_steps=0)
    with pytest.raises(ValueError, match="gamma"):
        AIRLConfig(gamma=1.5)
    with pytest.raises(ValueError, match="normalizer_warmup"):
        GAILConfig(normalizer_warmup=-1)
    env, buffer, _ = _cartpole(0)
    with pytest.raises(ValueError, match="GAILConfig"):
        gail(env, build("for_env", env, value=True), buffer, AIRLConfig())
    pend = make_env("Pendulum-v1", seed=0)
    with pytest.raises(ValueError, match="probabilistic"):
        AIRLDiscriminator(build("for_env", pend, value=True), gamma=0.9)  # deterministic head


# --------------------------------------------------- learning and reproducibility
def _greedy_returns(learner: ActorCritic) -> torch.Tensor:
    """``[20]`` returns of the greedy policy from the same 20 initial states."""
    env = make_env("CartPole-v1", seed=123)
    summary = episode_returns(env, learner.policy, 20, exploration=GREEDY, seed=123)
    return summary.returns


@pytest.mark.slow  # benchmarks/beyond_cloning.py measures GAIL on CartPole
def test_gail_improves_cartpole_over_its_initial_policy():
    env, buffer, learner = _cartpole(0)
    before = _greedy_returns(learner)
    result = gail(env, learner, buffer, GAILConfig(total_steps=2048, rollout_steps=1024, seed=0))
    after = _greedy_returns(learner)
    assert result.env_steps == 2048 and result.expert_queries == len(buffer) == 500
    assert result.expert_transitions == 499  # the cut end of the episode has no successor
    assert _mann_whitney_p(after, before) < 0.01, (before.tolist(), after.tolist())


@pytest.mark.parametrize("method", ["gail", "airl"])
def test_same_seed_same_numbers(method):
    extra = dict(grad_penalty=1.0, absorbing=True, normalizer_warmup=32, **TINY)

    def run():
        env, buffer, learner = _cartpole(3)
        if method == "gail":
            result = gail(env, learner, buffer, GAILConfig(**extra))
        else:
            result, _ = airl(env, learner, buffer, AIRLConfig(**extra))
        return result, learner, buffer

    (a, la, buffer), (b, lb, _) = run(), run()
    assert [(r.discriminator, r.generator, r.learned_reward) for r in a.rounds] == [
        (r.discriminator, r.generator, r.learned_reward) for r in b.rounds
    ]
    assert all(
        torch.equal(x, y) for x, y in zip(la.state_dict().values(), lb.state_dict().values())
    )
    assert len(a.rounds) == 2 and a.rounds[-1].discriminator["grad_penalty"] > 0
    # the random early policy drops the pole: absorbing rows and their reward
    assert a.rounds[0].terminated > 0 and a.rounds[0].absorbing_reward is not None
    # the warm-up's 32 steps are counted, and their states join the normaliser's statistics
    assert a.env_steps == 256 + 32 and a.rounds[0].env_steps == 128 + 32
    demo_std = buffer.data[keys.OBSERVATION].double().std(0, correction=0).float()
    assert not torch.allclose(la.normalizer.scale, demo_std, rtol=1e-3)


@pytest.mark.parametrize("anneal", [False, True])
def test_annealing_steps_round_k_of_k_at_one_minus_k_over_k(monkeypatch, anneal):
    from imitrl.algorithms.adversarial.generator import PPOGenerator

    seen, update = [], PPOGenerator.update

    def spy(self, batch, generator):
        seen.append([g["lr"] for o in (self.learner.opt_pi, self.learner.opt_v)
                     for g in o.param_groups])  # fmt: skip
        return update(self, batch, generator)

    monkeypatch.setattr(PPOGenerator, "update", spy)
    env, buffer, learner = _cartpole(3)
    budget = {**TINY, "total_steps": 4 * TINY["rollout_steps"]}
    result = gail(env, learner, buffer, GAILConfig(**budget, anneal_lr=anneal))
    assert len(result.rounds) == len(seen) == 4
    scales = [1 - k / 4 for k in range(4)] if anneal else [1.0] * 4
    assert seen == [[3e-4 * s, 3e-4 * s] for s in scales]
    # the learner keeps its own rate after the run
    assert [g["lr"] for g in learner.opt_pi.param_groups + learner.opt_v.param_groups] == [
        3e-4,
        3e-4,
    ]


def test_learning_rates_come_back_after_an_error():
    from imitrl.algorithms.adversarial.generator import PPOGenerator

    _, _, learner = _cartpole(0)
    gen = PPOGenerator(learner, gamma=0.99, gae_lambda=0.95, clip_epsilon=0.2,
                       entropy_coeff=0.0, epochs=1, minibatch_size=8, max_grad_norm=0.5)  # fmt: skip
    with pytest.raises(RuntimeError, match="boom"), gen.learning_rates(0.25):
        assert learner.opt_pi.param_groups[0]["lr"] == 3e-4 * 0.25
        raise RuntimeError("boom")
    assert learner.opt_pi.param_groups[0]["lr"] == learner.opt_v.param_groups[0]["lr"] == 3e-4


def test_learning_rates_scale_each_group_once_and_keep_a_tensor_rate():
    from imitrl.algorithms.adversarial.generator import PPOGenerator

    _, _, learner = _cartpole(0)
    params = list(learner.policy.parameters()) + list(learner.value.parameters())
    rate = torch.tensor(2e-3)
    shared = torch.optim.Adam([{"params": params[:2], "lr": rate}, {"params": params[2:]}], lr=1e-3)
    learner.opt_pi = learner.opt_v = shared  # one optimizer, two groups, both roles
    gen = PPOGenerator(learner, gamma=0.99, gae_lambda=0.95, clip_epsilon=0.2,
                       entropy_coeff=0.0, epochs=1, minibatch_size=8, max_grad_norm=0.5)  # fmt: skip
    with gen.learning_rates(0.5):
        assert torch.equal(shared.param_groups[0]["lr"], rate * 0.5)  # once, not x 0.25
        assert shared.param_groups[1]["lr"] == 5e-4
    assert shared.param_groups[0]["lr"] is rate and shared.param_groups[1]["lr"] == 1e-3


# ------------------------------------------------------------------- jobs
@pytest.mark.parametrize(("job", "run"), [(GAILJob, run_gail), (AIRLJob, run_airl)])
def test_jobs_write_results_and_a_loadable_checkpoint(tmp_path, job, run):
    config = job(max_episode_steps=50, eval_episodes=2, out=tmp_path, progress=False, **TINY)
    results = run(config)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["command"] == results["command"] == run.__name__.removeprefix("run_")
    assert saved["env_steps"] == 256 and saved["expert_queries"] == 50  # one 50-step demo
    assert len(saved["rounds"]) == 2 and "learner" in saved and "initial_learner" in saved
    learner = load_learner(tmp_path, make_env("CartPole-v1", seed=0))  # imitrl eval's path
    obs = torch.zeros(3, 4)
    torch.testing.assert_close(learner.probs(obs), _retrained(config).probs(obs))


def _retrained(config) -> ActorCritic:
    """The job's learner, trained again by the same flags (reproducibility of the job)."""
    env = make_env("CartPole-v1", seed=config.seed, max_episode_steps=50)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    # with each row's s', as the job keeps it: the cut episode's last row is a transition
    buffer.extend(rollout_episodes(env, cartpole_expert(), 1, next_observation=True))
    learner = build("for_env", env, lr=config.lr, seed=config.seed, value=True)
    train = gail if isinstance(config, GAILJob) and not isinstance(config, AIRLJob) else airl
    train(env, learner, buffer, config.algorithm_config())
    return learner


def test_absorbing_states_default_to_whether_a_demonstration_ends_by_termination(tmp_path):
    """--absorbing unset: on for Acrobot (the expert's episode ends at the goal), off for
    CartPole cut at 50 steps (truncated); the flag overrides either way."""
    from imitrl.algorithms.adversarial.absorbing import demonstrations_terminate

    rows = TensorDict({("next", "terminated"): torch.zeros(4, 1, dtype=torch.bool)}, [4])
    assert not demonstrations_terminate(rows)
    rows["next", "terminated"][2] = True
    assert demonstrations_terminate(rows)
    assert not demonstrations_terminate(TensorDict({}, [3]))  # the data says nothing
    cases = [
        (dict(env="Acrobot-v1", expert="acrobot"), True, "ends by termination"),
        (dict(max_episode_steps=50), False, "every demonstration is truncated"),
        (dict(max_episode_steps=50, absorbing=True), True, "--absorbing"),
    ]
    for i, (flags, on, why) in enumerate(cases):
        config = GAILJob(eval_episodes=1, out=tmp_path / str(i), progress=False,
                         **{**TINY, **flags})  # fmt: skip
        results = run_gail(config)
        assert results["absorbing"]["on"] is on and why in results["absorbing"]["why"]


def test_job_flags_are_checked(tmp_path):
    with pytest.raises(ValueError, match="demos"):
        GAILJob(demos=0)
    with pytest.raises(ValueError, match="--total-steps must be an integer >= 1"):
        AIRLJob(total_steps=0)  # the library's field, checked as the job's flag
    with pytest.raises(ValueError, match="log pi"):
        run_gail(
            GAILJob(env="Pendulum-v1", expert="pendulum", loss="mse", progress=False, out=tmp_path)
        )


@pytest.mark.parametrize(("job", "run"), [(GAILJob, run_gail), (AIRLJob, run_airl)])
def test_jobs_evaluate_during_training_and_log_their_losses(tmp_path, job, run):
    """eval/return at env step 0 and after every --eval-every rounds (and the last), the
    discriminator's and PPO's losses in the CSV scalars curves.png is drawn from."""
    config = job(max_episode_steps=50, eval_episodes=2, out=tmp_path, progress=False,
                 **{**TINY, "total_steps": 512, "eval_every": 2})  # fmt: skip
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*not exactly divisible")
        results = run(config)
    name = run.__name__.removeprefix("run_")
    evaluated = [r["env_steps"] for r in results["rounds"] if r["info"] is not None]
    assert evaluated == [256, 512]  # rounds 2 and 4 of 128 steps
    assert results["rounds"][-1]["info"]["evaluation"] == results["learner"]
    curves = read_scalars(scalars_dir(tmp_path, name))
    assert curves["eval/return"][0] == [0, 256, 512]
    assert curves["eval/return"][1][0] == results["initial_learner"]["mean_return"]
    for loss in ("discriminator_loss", "loss_objective", "loss_critic"):
        assert curves[f"{name}/{loss}"][0] == [128, 256, 384, 512]


def test_default_budget_is_whole_rounds():
    """TorchRL's collector warns "not exactly divisible" unless the budget is whole rounds."""
    for job in (GAILJob(), AIRLJob()):
        assert job.total_steps % job.rollout_steps == 0
    with pytest.raises(ValueError, match="eval-every"):
        GAILJob(eval_every=-1)


def test_a_cut_episode_end_with_a_recorded_next_observation_is_kept():
    """A review: a dataset of one-step truncated episodes (Minari records s') was refused,
    "no demonstration row has a known next observation"."""
    obs = torch.arange(10.0).reshape(5, 2)
    stored = torch.cat([obs[1:], torch.tensor([[99.0, 99.0]])])  # s' of each row
    stored[2] = torch.tensor([7.0, 7.0])  # episode 0 terminated there: s' never read
    rows = _two_episodes(obs, {(keys.NEXT, keys.OBSERVATION): stored})
    tr = expert_transitions(rows)  # episode 1's cut end kept, with its recorded s'
    assert tr.shape == (5,)
    torch.testing.assert_close(tr[NEXT_OBS][4], torch.tensor([99.0, 99.0]))
    torch.testing.assert_close(tr[NEXT_OBS][:2], obs[1:3])
    one_step = rows[[4]].clone()  # a dataset of one-step truncated episodes alone
    assert expert_transitions(one_step).shape == (1,)
    rows[(keys.NEXT, keys.OBSERVATION)][0] = torch.tensor([5.0, 5.0])  # disagrees with row 1
    with pytest.raises(ValueError, match=r"row 0 \(episode 0, step 0\): its recorded next"):
        expert_transitions(rows)

"""GAIL and AIRL on data-parallel ranks (issue 45): two gloo ranks each holding B of 2B
transitions take the discriminator step one process takes on all 2B; whole runs keep
every rank's networks equal while each rank plays its own lanes, and count every rank's
env steps."""

from __future__ import annotations

import pytest
import torch
import torch.multiprocessing as mp

from tests import _child

B, WORLD, LANES = 32, 2, 2
RUN = dict(total_steps=512, rollout_steps=128, ppo_epochs=2, minibatch_size=64,
           discriminator_updates=2, discriminator_batch=32)  # fmt: skip


def _demos(env_id: str, seed: int):
    from imitrl.data import DemonstrationBuffer
    from imitrl.envs import make_env
    from imitrl.experts import cartpole_expert, pendulum_expert
    from imitrl.runtime import rollout_episodes

    demo = make_env(env_id, seed=seed, max_episode_steps=200)
    expert = cartpole_expert() if env_id == "CartPole-v1" else pendulum_expert()
    buffer = DemonstrationBuffer(action_spec=demo.action_spec_unbatched)
    buffer.extend(rollout_episodes(demo, expert, 1))
    return demo, buffer


def _learner(env_id: str, demo):
    from imitrl.learners import build

    head = "categorical" if env_id == "CartPole-v1" else "tanh_normal"
    learner = build("for_env", demo, head=head, hidden=(16,), seed=0, value=True)
    return learner


def discriminator_steps(method: str, rows: slice) -> dict:
    """Five steps of ``method``'s discriminator (no gradient penalty: its interpolations
    are each rank's own draws) on rows ``rows`` of fixed expert and "policy" transitions
    (the policy side: another seed's demonstration); its parameters after."""
    from imitrl.algorithms.adversarial.absorbing import with_absorbing
    from imitrl.algorithms.adversarial.airl_discriminator import AIRLDiscriminator
    from imitrl.algorithms.adversarial.gail_discriminator import GAILDiscriminator
    from imitrl.algorithms.adversarial.transitions import expert_transitions

    env_id = "CartPole-v1" if method == "gail" else "Pendulum-v1"
    demo, expert = _demos(env_id, 0)
    _, other = _demos(env_id, 1)
    learner = _learner(env_id, demo)
    learner.prepare(expert.data)
    sides = [with_absorbing(expert_transitions(b.data))[: 2 * B][rows] for b in (expert, other)]
    if method == "gail":
        disc = GAILDiscriminator(learner, grad_penalty=0.0, seed=0)
        module = disc.module
    else:
        disc = AIRLDiscriminator(learner, gamma=0.99, grad_penalty=0.0, seed=0)
        module = disc.network
    for _ in range(5):
        disc.update(*sides)
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def whole_run(method: str, rank: int) -> dict:
    """A small run on ``LANES`` lanes seeded apart by rank (as ``imitrl gail`` seeds
    them): the learner's parameters, the normaliser's statistics, the rounds' records."""
    from imitrl.algorithms.adversarial import AIRLConfig, GAILConfig, airl, gail
    from imitrl.envs import make_env

    env_id = "CartPole-v1" if method == "gail" else "Pendulum-v1"
    demo, buffer = _demos(env_id, 0)
    learner = _learner(env_id, demo)
    env = make_env(env_id, seed=100 + rank * LANES, num_envs=LANES)
    if method == "gail":
        result = gail(env, learner, buffer, GAILConfig(**RUN))
    else:
        result, _ = airl(env, learner, buffer, AIRLConfig(**RUN, normalizer_warmup=64))
    norm = learner.normalizer
    return {
        "params": {k: v.detach().clone() for k, v in learner.policy.state_dict().items()},
        "value": {k: v.detach().clone() for k, v in learner.value.state_dict().items()},
        "norm": None if norm is None else {k: v.clone() for k, v in norm.state_dict().items()},
        "records": [(r.env_steps, r.learned_reward, r.terminated) for r in result.rounds],
        "env_steps": result.env_steps,
    }


def _rank(rank: int, world: int, init: str, out: str) -> None:
    import torch.distributed as dist

    from imitrl.system.ranks import share

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init}", rank=rank, world_size=world)
    try:
        first, count = share(2 * B, rank, world)
        got = {m: discriminator_steps(m, slice(first, first + count)) for m in ("gail", "airl")}
        got.update({f"{m}_run": whole_run(m, rank) for m in ("gail", "airl")})
        torch.save(got, f"{out}.{rank}")
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def ranks(tmp_path_factory):
    folder = tmp_path_factory.mktemp("adversarial_ranks")
    out = str(folder / "out.pt")
    mp.start_processes(
        _rank,
        args=(WORLD, str(folder / "init"), out),
        nprocs=WORLD,
        join=True,
        start_method=_child.forkserver(),
    )
    return [torch.load(f"{out}.{r}") for r in range(WORLD)]


def _relative(got: dict, want: dict) -> float:
    a = torch.cat([got[k].reshape(-1) for k in want])
    b = torch.cat([want[k].reshape(-1) for k in want])
    return ((a - b).norm() / b.norm()).item()


@pytest.mark.parametrize("method", ["gail", "airl"])
def test_two_ranks_discriminator_steps_are_one_process_on_both_halves(ranks, method):
    one = discriminator_steps(method, slice(0, 2 * B))
    assert _relative(ranks[0][method], one) <= 1e-6
    assert _relative(ranks[1][method], one) <= 1e-6
    half = discriminator_steps(method, slice(0, B))  # a rank alone: visibly elsewhere
    assert _relative(half, one) > 1e-3


@pytest.mark.parametrize("method", ["gail", "airl"])
def test_a_run_on_two_ranks_keeps_their_networks_equal_and_counts_both(ranks, method):
    runs = [r[f"{method}_run"] for r in ranks]
    for part in ("params", "value"):
        for key, value in runs[0][part].items():
            assert torch.equal(value, runs[1][part][key]), (part, key)
    if runs[0]["norm"] is not None:  # the warm-up's statistics: both ranks' steps
        for key, value in runs[0]["norm"].items():
            assert torch.equal(value, runs[1]["norm"][key]), key
    assert runs[0]["records"] == runs[1]["records"]  # every rank's rows, summed alike
    per_round = RUN["rollout_steps"] * WORLD
    steps = [s for s, _, _ in runs[0]["records"]]
    warmup = 64 * WORLD if method == "airl" else 0
    assert steps == [warmup + per_round * (k + 1) for k in range(len(steps))]
    assert runs[0]["env_steps"] == warmup + RUN["total_steps"]

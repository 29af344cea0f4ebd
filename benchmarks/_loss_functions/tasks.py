"""The tasks of ``loss_functions.py``: each one's spaces, expert, envs, score and budget."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from _common import DET, RND, Uniform, lake, returns, rollout
from imitrl import keys
from imitrl.algorithms import BCConfig
from imitrl.data.chunks import IS_INIT
from imitrl.envs import TabularEnv, make_env
from imitrl.envs import multimodal as mm
from imitrl.evaluation import exact_values
from imitrl.experts import cartpole_expert, inverted_pendulum_expert, pendulum_expert
from imitrl.objectives.registry import Learner, LearnerConfig, TaskSpec
from imitrl.policies import BetaMixer, Expert, as_actor, behaviour_policy
from imitrl.policies.chunking import chunk_env
from imitrl.tabular import greedy, success_probability

TASKS = ("frozenlake", "cartpole", "pendulum", "inverted_pendulum", "two_way")


# --------------------------------------------------------------------- protocol
@dataclass(frozen=True)
class Protocol:
    """One task's data and training budget (the same for every loss)."""

    demo_episodes: int
    """expert episodes in the BC dataset (DAgger's round 0)"""
    rounds: int
    """DAgger fits; round 0 is BC, the last is reported as DAgger"""
    episodes_per_round: int
    """learner episodes relabelled by the expert per DAgger round"""
    bc: BCConfig
    """every fit: gradient steps, batch size (the loss comes with the registry's learner)"""
    learner: LearnerConfig
    """network size, learning rate, normalisation shared by every loss (seeded per cell)"""
    eval_episodes: int
    """evaluation episodes per learner (gym and two-way tasks)"""
    max_episode_steps: int | None = None
    """cap on episode length (None: the env's own limit); used by --quick"""


def quick(protocol: Protocol) -> Protocol:
    """A smoke-test budget: tiny fits, two rounds, two short evaluation episodes."""
    return replace(
        protocol,
        demo_episodes=min(protocol.demo_episodes, 2),
        rounds=2,
        episodes_per_round=1,
        bc=replace(protocol.bc, num_steps=5),
        eval_episodes=2,
        max_episode_steps=30,
    )


# ------------------------------------------------------------------------ tasks
class Task:
    """A task of the benchmark: its spaces, expert, envs and score."""

    name: str
    score_name: str
    protocol: Protocol

    def spec(self) -> TaskSpec:
        raise NotImplementedError

    def expert(self) -> TensorDictModuleBase:
        """Writes ``EXPERT_ACTION`` (the queryable expert)."""
        raise NotImplementedError

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        raise NotImplementedError

    def max_steps(self) -> int:
        """Safety bound on steps per lane in one rollout."""
        raise NotImplementedError

    def score(self, policy: TensorDictModuleBase, exploration: ExplorationType, seed: int) -> dict:
        """``{"score": float, ...}`` of a policy writing ``ACTION``."""
        raise NotImplementedError

    def expert_score(self, seed: int) -> dict:
        return self.score(as_actor(self.expert()), DET, seed)

    def random_score(self, seed: int) -> dict:
        return self.score(Uniform(self.spec().action, seed), RND, seed)

    def extras(self, learner: Learner, seed: int) -> dict:
        return {}


class FrozenLake(Task):
    name, score_name = "frozenlake", "exact success"

    def __init__(self, protocol: Protocol) -> None:
        self.protocol = protocol
        self.mdp, self.Q = lake()  # Q*: [S, A] float64
        self.table = greedy(self.Q)

    def advantage(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``Q*(s, a) - mean_b Q*(s, b)``: how much better ``a`` is than a random choice."""
        return (self.Q[obs, action] - self.Q[obs].mean(-1)).float()

    def spec(self) -> TaskSpec:
        return TaskSpec(action=4, num_states=16, advantage=self.advantage)

    def expert(self) -> TensorDictModuleBase:
        return Expert.from_table(self.table)

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        return TabularEnv(self.mdp, batch_size=(lanes,), seed=seed)

    def max_steps(self) -> int:
        return 100_000

    def score(self, policy, exploration, seed) -> dict:
        exact = exact_values(self.mdp, policy, exploration, 100)
        return {"score": exact["success"], "exact_return": exact["return"]}

    def expert_score(self, seed: int) -> dict:
        return {"score": success_probability(self.mdp, self.table, 100)}

    def random_score(self, seed: int) -> dict:
        uniform = torch.full((16, 4), 0.25, dtype=torch.float64)
        return {"score": success_probability(self.mdp, uniform, 100)}


class Gym(Task):
    """A gymnasium task with a built-in expert; score = mean return over held-out episodes."""

    score_name = "return"

    def __init__(
        self, name: str, env_id: str, expert: Callable[[], Expert], protocol: Protocol
    ) -> None:
        self.name, self.env_id, self._expert, self.protocol = name, env_id, expert, protocol
        probe = make_env(env_id, seed=0)
        self._obs_dim = int(probe.observation_spec[keys.OBSERVATION].shape[-1])
        spec = probe.action_spec_unbatched
        self._action = int(spec.n) if not isinstance(spec, Bounded) else spec
        probe.close()

    def spec(self) -> TaskSpec:
        return TaskSpec(action=self._action, observation_dim=self._obs_dim)

    def expert(self) -> TensorDictModuleBase:
        return self._expert()

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        env = make_env(
            self.env_id,
            seed=seed,
            num_envs=lanes,
            max_episode_steps=self.protocol.max_episode_steps,
        )
        return chunk_env(env)  # is_init: where a chunked learner replans

    def max_steps(self) -> int:
        return 20_000

    def score(self, policy, exploration, seed) -> dict:
        n = self.protocol.eval_episodes
        env = self.env(seed=10_000 + 100 * seed, lanes=n)  # held-out starts
        r = returns(env, policy, n, exploration=exploration, max_steps=self.max_steps())
        env.close()
        return {"score": float(r.mean()), "returns": r.tolist()}


class TwoWay(Task):
    """:mod:`imitrl.envs.multimodal`: score = success rate; mode fractions at the decision states."""

    name, score_name = "two_way", "success"
    decision_states = 1000

    def __init__(self, protocol: Protocol | None) -> None:
        self.protocol = protocol
        self.geometry = mm.ObstacleGeometry()

    def spec(self) -> TaskSpec:
        return TaskSpec(action=Bounded(-1.0, 1.0, shape=(1,)), observation_dim=2)

    def expert(self) -> TensorDictModuleBase:
        return mm.two_way_expert(self.geometry)

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        env = mm.TwoWayObstacleEnv(batch_size=(lanes,), geometry=self.geometry, seed=seed)
        return chunk_env(env)  # is_init: where a chunked learner replans

    def max_steps(self) -> int:
        return 100 * self.geometry.steps

    def score(self, policy, exploration, seed) -> dict:
        # the expert rides along (beta = 0) only so that the rows carry its labels
        n = self.protocol.eval_episodes
        env = self.env(seed=10_000 + 100 * seed, lanes=min(n, 100))
        behaviour = behaviour_policy(self.expert(), policy, BetaMixer(0.0))
        rows = rollout(env, behaviour, n, exploration=exploration, max_steps=self.max_steps())
        success = rows.get((keys.NEXT, keys.REWARD)).reshape(-1) > 0
        side = mm.passing_side(rows, self.geometry)
        wins = int(success.sum())
        above = int(((side > 0) & _episode_success(rows)).sum())
        return {"score": wins / n, "passed_above": above / wins if wins else None}

    def extras(self, learner: Learner, seed: int) -> dict:
        obs = mm.decision_states(self.decision_states, geometry=self.geometry, seed=seed)
        out = {}
        for exploration, tag in (
            (learner.exploration, "modes"),
            (DET, "modes_det"),
            (RND, "modes_rnd"),
        ):
            with torch.no_grad(), set_exploration_type(exploration):
                # is_init: a chunked learner plans afresh at each state, acts its first action
                init = torch.ones(obs.shape[0], 1, dtype=torch.bool)
                td = TensorDict({keys.OBSERVATION: obs, IS_INIT: init}, batch_size=[obs.shape[0]])
                td = learner.policy(td)
            fractions = mm.mode_fractions(obs, td.get(keys.ACTION), geometry=self.geometry)
            out.update({f"{tag}_{k}": v for k, v in fractions.items()})
        return out


def _episode_success(rows: TensorDictBase) -> torch.Tensor:
    episode = rows.get(keys.EPISODE)
    reward = rows.get((keys.NEXT, keys.REWARD)).reshape(-1)
    ids = torch.unique(episode)
    return torch.stack([(reward[episode == e] > 0).any() for e in ids])


# ------------------------------------------------------------------- the table
def tasks(quick_mode: bool) -> dict[str, Callable[[], Task]]:
    """Each task's constructor by name, with its full (or, ``quick_mode``, smoke) budget."""

    def p(protocol: Protocol) -> Protocol:
        return quick(protocol) if quick_mode else protocol

    mlp = LearnerConfig(hidden=(64, 64), lr=1e-3)
    wide = LearnerConfig(hidden=(128, 128), lr=3e-3)
    return {
        "frozenlake": lambda: FrozenLake(
            p(
                Protocol(
                    demo_episodes=1,
                    rounds=4,
                    episodes_per_round=3,
                    bc=BCConfig(num_steps=200),
                    learner=LearnerConfig(lr=0.1),
                    eval_episodes=0,
                )
            )
        ),
        "cartpole": lambda: Gym(
            "cartpole",
            "CartPole-v1",
            cartpole_expert,
            p(Protocol(1, 4, 2, BCConfig(num_steps=1000, batch_size=256), mlp, 10)),
        ),
        "pendulum": lambda: Gym(
            "pendulum",
            "Pendulum-v1",
            pendulum_expert,
            p(Protocol(5, 4, 2, BCConfig(num_steps=2000, batch_size=256), wide, 10)),
        ),
        "inverted_pendulum": lambda: Gym(
            "inverted_pendulum",
            "InvertedPendulum-v5",
            inverted_pendulum_expert,
            p(Protocol(2, 4, 1, BCConfig(num_steps=2000, batch_size=256), wide, 10)),
        ),
        "two_way": lambda: TwoWay(
            p(Protocol(50, 4, 20, BCConfig(num_steps=3000, batch_size=256), wide, 100))
        ),
    }

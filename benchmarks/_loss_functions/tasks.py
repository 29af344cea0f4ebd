"""The tasks of ``loss_functions.py``: one registry of task definitions, built-in or from outside.

A task is a :class:`TaskDef`: an env (a gymnasium id, ``module:Id-v0`` whose import
registers it, or ``module:Class``, a TorchRL env class), where its demonstrations come
from (an expert ``module:function``, or a recorded LeRobot / Minari dataset, or both:
the dataset for round 0, the expert for DAgger's labels), how it is scored and its
budget (:class:`Protocol`). The built-in tasks are entries of :data:`TASKS` written
the same way; ``--task key=value,...`` (:func:`parse_task`) adds one from outside::

    --task name=pend,env=Pendulum-v1,expert=imitrl.experts:pendulum_expert,demos=5,steps=2000
    --task name=mine,env=mypkg.envs:Reach-v0,expert=mypkg.experts:act,expert_kind=callable
    --task name=rec,env=Pendulum-v1,dataset=/data/pendulum_lerobot,demos=10

:func:`build` turns a definition into a :class:`Task` (its spec, expert, envs, scores).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from _common import DET, RND, Uniform, returns, rollout, summaries
from imitrl import keys
from imitrl.algorithms import BCConfig
from imitrl.data.chunks import IS_INIT
from imitrl.envs import TabularEnv, make_env
from imitrl.envs.success import SUCCESS, reported_success
from imitrl.evaluation import exact_values
from imitrl.jobs.resolve import EXPERT_KINDS, load_dataset, make_expert
from imitrl.learners import Learner, TaskSpec
from imitrl.learners import build as build_learner
from imitrl.learners.defaults import HIDDEN
from imitrl.policies import BetaMixer, Expert, as_actor, behaviour_policy
from imitrl.policies.chunking import chunk_env
from imitrl.tabular import TabularMDP, greedy, success_probability, value_iteration

SCORES = ("return", "success", "exact")
"""``return``: mean episode return; ``success``: fraction of successful episodes (the
env's own ``("next", "success")`` flag where it reports one, as the Meta-World tasks do;
else a positive return); ``exact``: a tabular gymnasium env's success probability from
its MDP"""


# --------------------------------------------------------------------- protocol
@dataclass(frozen=True)
class LearnerSettings:
    """What a protocol sets of every loss's learner (``imitrl.learners.build``'s shared
    settings): each loss takes the ones it has, as the registry documents (a table has no
    hidden layers; ACT and Diffusion Policy train at their recipe's rate and widths)."""

    hidden: tuple[int, ...] = HIDDEN
    """hidden layers of the MLPs (the library's default width unless a task says)"""
    lr: float | None = None
    """Adam's rate (None: the network's default)"""
    seed: int = 0
    """initialisation seed (set per cell)"""
    normalize: bool = True
    """observations normalised by the demonstrations' statistics"""
    device: str | None = None
    """where the learner computes (None: the CPU)"""

    def build(self, loss: str, spec: TaskSpec) -> Learner:
        """``build(loss, spec, ...)`` with these settings where the loss takes them."""
        return build_learner(loss, spec, shared=asdict(self))


@dataclass(frozen=True)
class Protocol:
    """One task's data and training budget (the same for every loss)."""

    demo_episodes: int
    """expert episodes in the BC dataset (DAgger's round 0); a dataset's first episodes"""
    rounds: int
    """DAgger fits; round 0 is BC, the last is reported as DAgger (1: BC only)"""
    episodes_per_round: int
    """learner episodes relabelled by the expert per DAgger round"""
    bc: BCConfig
    """every fit: gradient steps, batch size (the loss comes with the registry's learner)"""
    learner: LearnerSettings
    """network size, learning rate, normalisation shared by every loss (seeded per cell)"""
    eval_episodes: int
    """evaluation episodes per learner (0 for ``exact``)"""
    max_episode_steps: int | None = None
    """cap on a gymnasium episode's length (None: the env's own limit); used by --quick"""
    round_steps: int | None = None
    """gradient steps of each relabel round's fit, continuing the previous round's
    learner (DAgger's warm start, as imitation's DAgger trains one policy throughout);
    None: every round refits a fresh learner for ``bc.num_steps``"""
    matched: bool = False
    """also fit BC on as many expert-driven rows as DAgger's last fit saw (its expert
    queries): BC at an equal query budget, reported as ``bc_matched``"""
    beta_decay: float | None = None
    """DAgger's beta schedule: None = 0 in every relabel round (the learner drives); p =
    Ross et al.'s ``beta_i = p ** (i - 1)`` (:class:`~imitrl.algorithms.beta_schedules.Exponential`:
    round 1 all expert, then the learner more and more)"""
    curve_points: int = 0
    """keep each reported fit's training loss as this many window means (a row's
    ``loss_curve``; 0: only its last step's, ``final_loss``)"""

    def __post_init__(self) -> None:
        if self.beta_decay is not None and not 0 <= self.beta_decay <= 1:
            raise ValueError(f"beta_decay must be in [0, 1] or None, got {self.beta_decay}")
        if self.curve_points < 0:
            raise ValueError(f"curve_points must be >= 0, got {self.curve_points}")
        if self.round_steps is not None and self.round_steps < 1:
            raise ValueError(
                f"round_steps must be a positive number of steps or None, got {self.round_steps}"
            )


def quick(protocol: Protocol) -> Protocol:
    """A smoke-test budget: tiny fits, two rounds, two short evaluation episodes."""
    return replace(
        protocol,
        demo_episodes=min(protocol.demo_episodes, 2),
        rounds=min(protocol.rounds, 2),
        episodes_per_round=1,
        bc=replace(protocol.bc, num_steps=5),
        round_steps=None if protocol.round_steps is None else 3,
        eval_episodes=min(protocol.eval_episodes, 2),
        max_episode_steps=30,
    )


# ----------------------------------------------------------------- definitions
@dataclass(frozen=True)
class TaskDef:
    """A task of the benchmark: its env, its demonstrations, its score and its budget."""

    name: str
    """row label in the tables"""
    env: str
    """a gymnasium id; ``module:Id-v0`` (importing ``module`` registers the id); or
    ``module:Class``, a TorchRL ``EnvBase`` subclass built as ``Class(batch_size=(n,),
    seed=s)`` (its observation a vector under ``"observation"``)"""
    protocol: Protocol
    """data and training budget"""
    expert: str | None = None
    """``module:function`` (what it is: ``expert_kind``); None: the dataset alone, BC only"""
    expert_kind: str = "builder"
    """``builder`` (``function()`` returns a module writing ``expert_action``) or
    ``callable`` (a batched ``obs -> action``), as ``imitrl bc --expert-kind``"""
    dataset: str | None = None
    """a LeRobot or Minari dataset directory: round 0's demonstrations (its first
    ``demo_episodes`` episodes) instead of the expert's rollouts"""
    score: str = "return"
    """one of :data:`SCORES`"""
    max_steps: int = 20_000
    """most steps one episode may take (a safety net; gymnasium ids stop at their limit)"""
    probe: str | None = None
    """``module:function``, ``probe(act, seed) -> {name: value}``: ``act(obs [N, d]) ->
    actions [N, m]`` runs the learner at the task's decision states (mode fractions)"""
    outcome: str | None = None
    """``module:function``, ``outcome(rows) -> {name: value}`` of the evaluation
    episodes' rows (needs an expert: it rides along to label the rows)"""
    in_default_run: bool = True
    """run when ``--tasks`` is not given"""

    def __post_init__(self) -> None:
        if self.score not in SCORES:
            raise ValueError(f"task {self.name}: score must be one of {SCORES}, got {self.score!r}")
        if self.expert_kind not in EXPERT_KINDS:
            raise ValueError(f"task {self.name}: expert_kind must be one of {EXPERT_KINDS}")
        if self.score == "exact":
            if self.expert is not None or self.dataset is not None:
                raise ValueError(
                    f"task {self.name}: an exact (tabular) task's expert is value iteration's "
                    "policy: give neither expert nor dataset"
                )
        elif self.expert is None and self.dataset is None:
            raise ValueError(f"task {self.name}: give an expert (module:function) or a dataset")
        if self.expert is None and self.score != "exact" and self.protocol.rounds > 1:
            raise ValueError(f"task {self.name}: DAgger (rounds > 1) needs an expert")
        if self.outcome is not None and self.expert is None:
            raise ValueError(f"task {self.name}: an outcome function needs an expert to ride along")


TASKS: dict[str, TaskDef] = {}
"""the built-in tasks, by name, in table order"""


def register_task(defn: TaskDef) -> TaskDef:
    """Add a task to :data:`TASKS` (ValueError if the name is taken)."""
    if defn.name in TASKS:
        raise ValueError(f"a task named {defn.name!r} is already registered")
    TASKS[defn.name] = defn
    return defn


# The budgets keep the default full run (5 seeds, every loss, --jobs 2) under 30
# minutes on 2 CPU cores. A DAgger relabel round continues the previous round's learner
# for `round_steps` steps (warm start) instead of refitting from scratch; Pendulum and
# the multimodal tasks run one relabel round with more episodes. The multimodal tasks
# train at lr 1e-2: at 3e-3 a flow-matching chunk policy was still underfitted after
# 2000 x 256 steps (two-way success 0.87 against 0.93 at 1e-2, 5 seeds; 1200 steps:
# 0.70-0.79; benchmarks/README.md).
_WIDE = LearnerSettings(hidden=(128, 128), lr=3e-3)
_FAST = LearnerSettings(hidden=(128, 128), lr=1e-2)
register_task(
    TaskDef(
        "frozenlake",
        env="FrozenLake-v1",
        score="exact",
        max_steps=100_000,
        protocol=Protocol(
            1, 4, 3, BCConfig(num_steps=200, batch_size=None), LearnerSettings(lr=0.1), 0
        ),
    )
)
register_task(
    TaskDef(
        "cartpole",
        env="CartPole-v1",
        expert="imitrl.experts:cartpole_expert",
        protocol=Protocol(
            1,
            4,
            2,
            BCConfig(num_steps=1000, batch_size=256),
            LearnerSettings((64, 64), 1e-3),
            10,
            round_steps=300,
        ),
    )
)
register_task(
    TaskDef(
        "pendulum",
        env="Pendulum-v1",
        expert="imitrl.experts:pendulum_expert",
        protocol=Protocol(
            5, 2, 4, BCConfig(num_steps=1000, batch_size=256), _WIDE, 10, round_steps=500
        ),
    )
)
register_task(
    TaskDef(
        "inverted_pendulum",
        env="InvertedPendulum-v5",
        expert="imitrl.experts:inverted_pendulum_expert",
        protocol=Protocol(2, 2, 2, BCConfig(num_steps=1000, batch_size=256), _WIDE, 10),
        # every loss tied here (BC about 0.01, DAgger 1.00 normalised, 5 seeds, 2000-step
        # fits): it cannot tell losses apart, so the full run leaves it out (--tasks adds it)
        in_default_run=False,
    )
)
register_task(
    TaskDef(
        "two_way",
        env="imitrl.envs.multimodal:TwoWayObstacleEnv",
        expert="imitrl.envs.multimodal:two_way_expert",
        score="success",
        max_steps=4_000,
        probe="imitrl.envs.multimodal:two_way_probe",
        outcome="imitrl.envs.multimodal:two_way_outcome",
        protocol=Protocol(
            50, 2, 40, BCConfig(num_steps=2000, batch_size=256), _FAST, 100, round_steps=500
        ),
    )
)
register_task(
    TaskDef(
        "corridor",
        env="imitrl.envs.corridor:ForkingCorridorEnv",
        expert="imitrl.envs.corridor:corridor_expert",
        score="success",
        max_steps=4_000,
        probe="imitrl.envs.corridor:corridor_probe",
        outcome="imitrl.envs.corridor:corridor_outcome",
        protocol=Protocol(
            50, 2, 40, BCConfig(num_steps=1000, batch_size=256), _FAST, 100, round_steps=300
        ),
    )
)


# ------------------------------------------------ names a task or an env may give
def _import(spec: str, what: str) -> object:
    module, sep, attr = spec.partition(":")
    if not sep or not module or not attr:
        raise ValueError(f"{what} {spec!r}: expected module:name")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"{what} {spec!r}: {err}") from err


def _env_class(env: str) -> type[EnvBase] | None:
    """The TorchRL env class ``env`` names (``module:Class``), or None for a gymnasium id."""
    module, sep, attr = env.partition(":")
    if not sep:
        return None
    try:
        obj = getattr(importlib.import_module(module), attr, None)
    except ImportError as err:
        raise ValueError(f"env {env!r}: cannot import {module!r} ({err})") from err
    return obj if isinstance(obj, type) and issubclass(obj, EnvBase) else None


# ------------------------------------------------------------------------ tasks
class Task:
    """A built :class:`TaskDef`: its spec, expert, envs, demonstrations and scores."""

    def __init__(self, defn: TaskDef, protocol: Protocol) -> None:
        self.defn, self.name, self.protocol = defn, defn.name, protocol
        self.score_name = {"return": "return", "success": "success", "exact": "exact success"}[
            defn.score
        ]

    def spec(self) -> TaskSpec:
        raise NotImplementedError

    def expert(self) -> TensorDictModuleBase | None:
        """Writes ``EXPERT_ACTION`` (the queryable expert); None for a dataset-only task."""
        raise NotImplementedError

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        raise NotImplementedError

    def max_steps(self) -> int:
        return self.defn.max_steps

    def demonstrations(self, env: EnvBase) -> TensorDictBase | None:
        """Round 0's rows from the dataset, or None (the expert drives instead)."""
        return None

    def score(self, policy: TensorDictModuleBase, exploration: ExplorationType, seed: int) -> dict:
        """``{"score": float, ...}`` of a policy writing ``ACTION``."""
        raise NotImplementedError

    def expert_score(self, seed: int) -> dict:
        return self.score(as_actor(self.expert()), DET, seed)

    def random_score(self, seed: int) -> dict:
        return self.score(Uniform(self.spec().action, seed), RND, seed)

    def extras(self, learner: Learner, seed: int) -> dict:
        return {}


class TabularTask(Task):
    """A tabular gymnasium env (``score="exact"``): exact success from its MDP, the expert
    value iteration's greedy policy."""

    def __init__(self, defn: TaskDef, protocol: Protocol) -> None:
        super().__init__(defn, protocol)
        self.mdp = TabularMDP.from_gym(defn.env, 0.95)
        self.Q = self.mdp.backup(value_iteration(self.mdp, 1000)[-1])  # Q*: [S, A] float64
        self.table = greedy(self.Q)

    def advantage(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``Q*(s, a) - mean_b Q*(s, b)``: how much better ``a`` is than a random choice."""
        return (self.Q[obs, action] - self.Q[obs].mean(-1)).float()

    def spec(self) -> TaskSpec:
        S, A = self.Q.shape
        return TaskSpec(action=int(A), num_states=int(S), advantage=self.advantage)

    def expert(self) -> TensorDictModuleBase:
        return Expert.from_table(self.table)

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        return TabularEnv(self.mdp, batch_size=(lanes,), seed=seed)

    def score(self, policy, exploration, seed) -> dict:
        exact = exact_values(self.mdp, policy, exploration, 100)
        return {"score": exact["success"], "exact_return": exact["return"]}

    def expert_score(self, seed: int) -> dict:
        return {"score": success_probability(self.mdp, self.table, 100)}

    def random_score(self, seed: int) -> dict:
        S, A = self.Q.shape
        uniform = torch.full((S, A), 1.0 / A, dtype=torch.float64)
        return {"score": success_probability(self.mdp, uniform, 100)}


class EnvTask(Task):
    """A gymnasium id or a TorchRL env class; score: mean return or success rate over
    evaluation episodes from held-out starts; optional probe and outcome diagnostics."""

    def __init__(self, defn: TaskDef, protocol: Protocol) -> None:
        super().__init__(defn, protocol)
        self._class = _env_class(defn.env)
        probe = self.env(seed=0, lanes=1)
        self._spec = TaskSpec.from_env(probe)
        probe.close()
        self._probe = _import(defn.probe, "probe") if defn.probe else None
        self._outcome = _import(defn.outcome, "outcome") if defn.outcome else None

    def spec(self) -> TaskSpec:
        return self._spec

    def expert(self) -> TensorDictModuleBase | None:
        if self.defn.expert is None:
            return None
        # a built-in name or module:function; the env id for experts made per env
        # (metaworld: the task's scripted policy)
        return make_expert(self.defn.expert, self.defn.expert_kind, env_id=self.defn.env)

    def env(self, *, seed: int, lanes: int) -> EnvBase:
        if self._class is not None:
            env = self._class(batch_size=(lanes,), seed=seed)
        else:
            env = make_env(
                self.defn.env,
                seed=seed,
                num_envs=lanes,
                max_episode_steps=self.protocol.max_episode_steps,
            )
        return chunk_env(env)  # is_init: where a chunked learner replans

    def demonstrations(self, env: EnvBase) -> TensorDictBase | None:
        if self.defn.dataset is None:
            return None
        rows = load_dataset(Path(self.defn.dataset), env)
        first = torch.unique(rows.get(keys.EPISODE))[: self.protocol.demo_episodes]
        return rows[torch.isin(rows.get(keys.EPISODE), first)]

    def score(self, policy, exploration, seed) -> dict:
        n = self.protocol.eval_episodes
        env = self.env(seed=10_000 + 100 * seed, lanes=min(n, 100))  # held-out starts
        out: dict = {}
        if self._outcome is not None:
            # the expert rides along (beta = 0) only so that the rows carry its labels
            behaviour = behaviour_policy(self.expert(), policy, BetaMixer(0.0))
            rows = rollout(env, behaviour, n, exploration=exploration, max_steps=self.max_steps())
            r = _episode_returns(rows)
            out.update(self._outcome(rows))
        elif SUCCESS in env.observation_spec.keys():  # the env reports success itself
            summary = summaries(
                env,
                policy,
                n,
                exploration=exploration,
                max_steps=self.max_steps(),
                success_fn=reported_success,
            )
            r, flags = summary.returns, summary.success
            out.update(
                successes=int(flags.sum()),
                episodes=n,
                mean_length=float(summary.lengths.double().mean()),
            )
        else:
            r = returns(env, policy, n, exploration=exploration, max_steps=self.max_steps())
        env.close()
        if self.defn.score == "success" and "successes" in out:
            out["score"] = out["successes"] / n
        elif self.defn.score == "success":
            out["score"] = float((r > 0).double().mean())
        else:
            out.update(score=float(r.mean()), returns=r.tolist())
        return out

    def expert_score(self, seed: int) -> dict:
        if self.defn.expert is not None:
            return super().expert_score(seed)
        # a dataset-only task: the demonstrator's own episodes are the reference
        env = self.env(seed=seed, lanes=1)
        r = _episode_returns(self.demonstrations(env))
        env.close()
        return {
            "score": float((r > 0).double().mean() if self.defn.score == "success" else r.mean())
        }

    def extras(self, learner: Learner, seed: int) -> dict:
        """The probe's numbers as the learner acts, greedily and sampled (``modes*``)."""
        if self._probe is None:
            return {}
        out = {}
        for exploration, tag in (
            (learner.exploration, "modes"),
            (DET, "modes_det"),
            (RND, "modes_rnd"),
        ):

            def act(obs: torch.Tensor, exploration=exploration) -> torch.Tensor:
                with torch.no_grad(), set_exploration_type(exploration):
                    # is_init: a chunked learner plans afresh at each state, acts its first action
                    init = torch.ones(obs.shape[0], 1, dtype=torch.bool)
                    td = TensorDict({keys.OBSERVATION: obs, IS_INIT: init}, [obs.shape[0]])
                    return learner.policy(td).get(keys.ACTION)

            out.update({f"{tag}_{k}": v for k, v in self._probe(act, seed).items()})
        return out


def _episode_returns(rows: TensorDictBase) -> torch.Tensor:
    """``[E]`` float64 undiscounted return of each episode in ``rows``, in id order."""
    episode = rows.get(keys.EPISODE)
    reward = rows.get((keys.NEXT, keys.REWARD)).reshape(-1).double()
    ids, inverse = torch.unique(episode, return_inverse=True)
    return torch.zeros(ids.numel(), dtype=torch.float64).index_add_(0, inverse, reward)


def build(defn: TaskDef, quick_mode: bool = False) -> Task:
    """The task of ``defn``, with its full (or, ``quick_mode``, smoke) budget."""
    protocol = quick(defn.protocol) if quick_mode else defn.protocol
    return (TabularTask if defn.score == "exact" else EnvTask)(defn, protocol)


def tasks(quick_mode: bool) -> dict[str, Callable[[], Task]]:
    """Each built-in task's constructor by name (kept for scripts that name tasks)."""
    return {name: (lambda d=defn: build(d, quick_mode)) for name, defn in TASKS.items()}

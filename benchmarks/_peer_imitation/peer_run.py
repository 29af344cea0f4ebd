"""imitation's side of ``peer_imitation.py``: runs in the PEER's venv, never in imitrl's.

It imports nothing from this repository (the peer's venv has no imitrl): the task
arrives as JSON (``tasks.Task.spec``) and the experts are written out again here, line
for line the same functions as ``imitrl.experts`` and imitrl's value iteration;
``peer_imitation.py`` checks that both label a batch of observations identically
before it times anything.

    PEER_PYTHON peer_run.py run SPEC_JSON RESULT_JSON    # one (task, seed) run
    PEER_PYTHON peer_run.py check OBS_JSON RESULT_JSON   # the experts' labels on a batch

A run is imitation's documented pipeline with the task's budgets:

1. setup: ``imitation.util.util.make_vec_env`` (``RolloutInfoWrapper``): one env for
   training, ``eval_lanes["imitation"]`` (50, as imitation's scripts) for evaluation; the expert as a Stable-Baselines3 ``BasePolicy``, the
   demonstrations from ``rollout.generate_trajectories`` (cut to ``demo_steps``);
2. bc: ``bc.BC`` (its default policy, ``FeedForward32Policy``: [32, 32] tanh) trained
   ``bc_steps`` batches on the demonstrations;
3. dagger: ``dagger.SimpleDAggerTrainer`` built on that BC trainer with the
   demonstrations as its round-0 data (protocol ``own``: imitation's default beta
   schedule, ``LinearBetaSchedule(15)``; ``matched``: beta 0; both with its warm start,
   one policy trained on), then
   ``rounds`` rounds of what ``SimpleDAggerTrainer.train`` does in a round, with the
   round count fixed instead of a timestep budget: ``episodes_per_round`` episodes
   through the trainer's ``InteractiveTrajectoryCollector``, then
   ``extend_and_update`` for ``round_steps`` batches;
4. evaluation: the BC policy and the final policy, greedy
   (``stable_baselines3...evaluate_policy``, ``deterministic=True``), ``eval_episodes``
   each on the evaluation vector env seeded ``eval_seed``.

Both sides are run quiet: imitation's logger writes no output formats, BC shows no
progress bar and DAgger's fits roll out no logging episodes (``log_rollouts_venv=None``;
its default would add 5 episodes to every 500 batches), as imitrl prints nothing by
default.
"""

import time

T_START = time.perf_counter()

import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

import gymnasium as gym  # noqa: E402
from imitation.algorithms import bc, dagger  # noqa: E402
from imitation.data import rollout, types  # noqa: E402
from imitation.data.wrappers import RolloutInfoWrapper  # noqa: E402
from imitation.util import logger as imit_logger  # noqa: E402
from imitation.util.util import make_vec_env  # noqa: E402
from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.common.policies import BasePolicy  # noqa: E402

T_IMPORTED = time.perf_counter()


# ----------------------------------------------------------------- the experts
# The same functions as imitrl's, in numpy (float64 where imitrl computes in float64).
CARTPOLE_GAINS = np.array([0.5, 1.0, 10.0, 2.0], dtype=np.float32)
"""imitrl.experts.CARTPOLE_GAINS: push right when K . obs > 0"""


def cartpole_act(obs: np.ndarray) -> np.ndarray:
    """``a = 1[K . obs > 0]`` on float32 observations ``[N, 4]`` -> int64 ``[N]``."""
    return ((obs.astype(np.float32) * CARTPOLE_GAINS).sum(-1) > 0).astype(np.int64)


def dlqr(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``imitrl.experts.dlqr``: the LQR gain ``K`` ``[m, n]`` by the same doubling iteration."""
    n = A.shape[0]
    eye = np.eye(n)
    Ak, Gk, Hk = A.copy(), B @ np.linalg.solve(R, B.T), Q.copy()
    for _ in range(64):
        W = np.linalg.solve(eye + Gk @ Hk, np.concatenate([Ak, Gk], axis=1))
        WA, WG = W[:, :n], W[:, n:]
        H_next = Hk + Ak.T @ Hk @ WA
        Gk = Gk + Ak @ WG @ Ak.T
        Ak = Ak @ WA
        H_next = (H_next + H_next.T) / 2
        done = np.abs(H_next - Hk).max() <= 1e-14 * np.abs(H_next).max()
        Hk = H_next
        if done:
            return np.linalg.solve(R + B.T @ Hk @ B, B.T @ Hk @ A)
    raise ValueError("the Riccati iteration did not converge")


def pendulum_gain() -> np.ndarray:
    """imitrl's ``PendulumSwingUp`` gain: LQR at the top of Pendulum-v1 under its cost."""
    g, m, length, dt = 10.0, 1.0, 1.0, 0.05
    a, b = 3 * g / (2 * length), 3 / (m * length * length)
    A = np.array([[1 + a * dt * dt, dt], [a * dt, 1.0]])
    B = np.array([[b * dt * dt], [b * dt]])
    # imitrl builds Q and R as float32 tensors, then solves in float64: the same here
    Q = np.diag(np.array([1.0, 0.1], dtype=np.float32)).astype(np.float64)
    R = np.array([[0.001]], dtype=np.float32).astype(np.float64)
    return dlqr(A, B, Q, R)[0]


PENDULUM_GAIN = pendulum_gain()


def pendulum_act(obs: np.ndarray) -> np.ndarray:
    """Energy-shaping swing-up, LQR inside ``cos th > 0.9``: ``[N, 3]`` -> float32 ``[N, 1]``."""
    obs = obs.astype(np.float64)
    c, s, w = obs[..., 0], obs[..., 1], obs[..., 2]
    th = np.arctan2(s, c)
    u_lqr = -(PENDULUM_GAIN[0] * th + PENDULUM_GAIN[1] * w)
    energy = w * w / 2 - 15.0 * (1 - c)
    u_swing = -1.0 * w * energy
    u_swing = np.where(np.abs(w) < 1e-3, 2.0, u_swing)  # at rest: push to start the swing
    u = np.where(c > 0.9, u_lqr, u_swing)
    return np.clip(u, -2.0, 2.0).astype(np.float32)[..., None]


def frozenlake_table(env_id: str = "FrozenLake-v1") -> np.ndarray:
    """Greedy actions ``[S]`` of ``Q = r + (gamma P) @ V_1000`` (gamma 0.95), as imitrl's
    ``greedy(mdp.backup(value_iteration(mdp, 1000)[-1]))``; ties to the lowest action."""
    model = gym.make(env_id).unwrapped.P
    S, A = len(model), len(model[0])
    P, r = np.zeros((S, A, S)), np.zeros((S, A))
    for s in range(S):
        for a in range(A):
            for p, s_next, reward, _ in model[s][a]:
                P[s, a, s_next] += p
                r[s, a] += p * reward
    gamma_P, V = 0.95 * P, np.zeros(S)
    for _ in range(1000):
        V = (r + gamma_P @ V).max(axis=1)
    return (r + gamma_P @ V).argmax(axis=1)


class ScriptedExpert(BasePolicy):
    """A batched ``obs -> action`` numpy function as a Stable-Baselines3 policy."""

    def __init__(self, observation_space, action_space, act) -> None:
        super().__init__(observation_space, action_space)
        self.act = act

    def _predict(self, observation: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        return torch.as_tensor(self.act(observation.cpu().numpy()))


def expert_function(env_id: str):
    if env_id == "FrozenLake-v1":
        table = frozenlake_table(env_id)
        return lambda obs: table[np.asarray(obs, dtype=np.int64)]
    return {"CartPole-v1": cartpole_act, "Pendulum-v1": pendulum_act}[env_id]


# -------------------------------------------------------------------------- run
def make_venv(env_id: str, seed: int, n_envs: int = 1):
    """``n_envs`` envs in imitation's ``make_vec_env`` (DummyVecEnv, Monitor, RolloutInfoWrapper)."""
    return make_vec_env(
        env_id,
        rng=np.random.default_rng(seed),
        n_envs=n_envs,
        post_wrappers=[lambda env, _: RolloutInfoWrapper(env)],
    )


def mean_return(policy, venv, episodes: int, seed: int) -> float:
    """Greedy mean return over ``episodes`` from the reset seed ``seed``."""
    venv.seed(seed)
    rewards, _ = evaluate_policy(
        policy,
        venv,
        n_eval_episodes=episodes,
        deterministic=True,
        return_episode_rewards=True,
        warn=False,
    )
    return float(np.mean(rewards))


def zero_beta(round_num: int) -> float:
    """The matched protocol's beta: the learner drives every relabel round."""
    return 0.0


def greedy_table(policy, num_states: int) -> list[int]:
    return policy.predict(np.arange(num_states), deterministic=True)[0].astype(int).tolist()


def run(spec: dict) -> dict:
    """One run; the phases in seconds, the returns, FrozenLake's greedy tables."""
    now = time.perf_counter
    seed, eval_seed, env_id = spec["seed"], spec["eval_seed"], spec["env_id"]
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    quiet = imit_logger.configure(tempfile.mkdtemp(prefix="peer-imitation-log-"), [])

    # -- setup: envs, expert, demonstrations
    t0 = now()
    venv = make_venv(env_id, seed)
    eval_venv = make_venv(
        env_id, eval_seed, min(spec["eval_lanes"]["imitation"], spec["eval_episodes"])
    )
    expert = ScriptedExpert(venv.observation_space, venv.action_space, expert_function(env_id))
    demos = _demonstrations(spec, venv, expert, rng)
    transitions = rollout.flatten_trajectories(demos)
    setup = now() - t0

    # -- BC
    t0 = now()
    trainer = bc.BC(
        observation_space=venv.observation_space,
        action_space=venv.action_space,
        rng=rng,
        demonstrations=transitions,
        batch_size=spec["batch_size"],
        custom_logger=quiet,
        device="cpu",
    )
    trainer.train(n_batches=spec["bc_steps"], progress_bar=False)
    bc_s = now() - t0

    evals: dict[str, float] = {}
    tables: dict[str, list[int]] = {}
    t0 = now()
    evals["bc"] = mean_return(trainer.policy, eval_venv, spec["eval_episodes"], eval_seed)
    if env_id == "FrozenLake-v1":
        tables["bc"] = greedy_table(trainer.policy, venv.observation_space.n)
    eval_s = now() - t0

    # -- DAgger: SimpleDAggerTrainer.train's round, a fixed number of times
    t0 = now()
    rows, collect_s, fit_s = _dagger(spec, venv, expert, rng, demos, trainer, quiet)
    rows += len(transitions)
    dagger_s = now() - t0
    t0 = now()
    evals["final"] = mean_return(trainer.policy, eval_venv, spec["eval_episodes"], eval_seed)
    if env_id == "FrozenLake-v1":
        tables["final"] = greedy_table(trainer.policy, venv.observation_space.n)
    eval_s += now() - t0
    return {
        "library": "imitation",
        "phases": {
            "imports": T_IMPORTED - T_START,
            "setup": setup,
            "bc": bc_s,
            "dagger": dagger_s,
            "dagger_fit": fit_s,
            "dagger_collect": collect_s,
            "evaluation": eval_s,
        },
        "returns": evals,
        "greedy_tables": tables,
        "rows": rows,
        "demo_rows": len(transitions),
    }


def _demonstrations(spec: dict, venv, expert, rng: np.random.Generator) -> list:
    """``spec["demo_episodes"]`` greedy expert episodes; the first ``spec["demo_steps"]``
    steps of the one episode where that is set."""
    demos = rollout.generate_trajectories(
        expert,
        venv,
        rollout.make_min_episodes(spec["demo_episodes"]),
        rng,
        deterministic_policy=True,
    )
    if spec["demo_steps"] is not None:
        k = spec["demo_steps"]
        (traj,) = demos
        demos = [
            types.TrajectoryWithRew(
                obs=traj.obs[: k + 1],
                acts=traj.acts[:k],
                infos=None if traj.infos is None else traj.infos[:k],
                terminal=False,
                rews=traj.rews[:k],
            )
        ]
    return demos


def _dagger(spec: dict, venv, expert, rng, demos, trainer, quiet) -> tuple[int, float, float]:
    """DAgger: ``SimpleDAggerTrainer.train``'s round, ``spec["rounds"]`` times. Returns the
    rows its rounds added, the seconds of collection (the trainer's set-up included) and
    of fitting."""
    now = time.perf_counter
    collect_s = fit_s = 0.0
    rows = 0
    t0 = now()
    scratch = tempfile.mkdtemp(prefix="peer-imitation-dagger-")
    dagger_trainer = dagger.SimpleDAggerTrainer(
        venv=venv,
        scratch_dir=scratch,
        expert_policy=expert,
        rng=rng,
        expert_trajs=demos,
        bc_trainer=trainer,
        custom_logger=quiet,
        # matched protocol: beta 0, as imitrl's default; own: imitation's LinearBetaSchedule(15)
        **({"beta_schedule": zero_beta} if spec["protocol"] == "matched" else {}),
    )
    collect_s += now() - t0  # the trainer's set-up
    for _ in range(spec["rounds"]):
        t = now()
        collector = dagger_trainer.create_trajectory_collector()
        trajs = rollout.generate_trajectories(
            policy=expert,
            venv=collector,
            sample_until=rollout.make_min_episodes(spec["episodes_per_round"]),
            rng=collector.rng,
            deterministic_policy=True,
        )
        collect_s += now() - t
        rows += sum(len(traj) for traj in trajs)
        t = now()
        dagger_trainer.extend_and_update(
            {"n_batches": spec["round_steps"], "progress_bar": False, "log_rollouts_venv": None}
        )
        fit_s += now() - t
    return rows, collect_s, fit_s


def check(batches: dict) -> dict:
    """The experts' labels on the parent's observation batches, ``{env_id: [N] or [N, 1]}``."""
    out = {}
    for env_id, obs in batches.items():
        venv = make_venv(env_id, 0)
        expert = ScriptedExpert(venv.observation_space, venv.action_space, expert_function(env_id))
        out[env_id] = expert.predict(np.asarray(obs), deterministic=True)[0].tolist()
    return out


def main() -> None:
    mode = sys.argv[1]
    if mode == "run":
        out = run(json.loads(sys.argv[2]))
        out["phases"]["in_process"] = time.perf_counter() - T_START
    elif mode == "check":
        out = check(json.loads(Path(sys.argv[2]).read_text()))
    else:
        raise SystemExit(f"unknown mode {mode!r}: run or check")
    Path(sys.argv[-1]).write_text(json.dumps(out))


if __name__ == "__main__":
    main()

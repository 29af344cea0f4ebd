"""imitation's GAIL and AIRL side of ``peer_imitation.py --gail``: runs in the PEER's venv.

    PEER_PYTHON gail_peer.py SPEC_JSON RESULT_JSON

``SPEC_JSON`` is :meth:`gail_tasks.GailTask.spec`, its ``settings`` imitation's GAIL
tutorial (``docs/tutorials/3_train_gail``); the run is the tutorial's with the task's
env, budget and demonstrations:

1. setup: ``make_vec_env`` with ``lanes`` envs (``RolloutInfoWrapper``), the scripted
   expert (``peer_run``'s copy of imitrl's), ``demo_episodes`` greedy expert episodes
   (``rollout.rollout``, the first ones to finish);
2. train: Stable-Baselines3 ``PPO(MlpPolicy, batch_size=64, ent_coef=0.0, n_epochs=5)``
   with the task's learning rate and discount and ``n_steps = rollout_steps / lanes``
   (one GAIL round = ``rollout_steps`` env steps, as on imitrl's side);
   ``BasicRewardNet`` with ``RunningNorm`` inputs (its default hidden layers 32, 32;
   Adam at its default 1e-3); ``GAIL(demo_batch_size=1024,
   gen_replay_buffer_capacity=512, n_disc_updates_per_round=8)`` (``allow_variable_horizon``
   on CartPole, whose episodes end when the pole falls); ``train(total_steps)``;
   An AIRL task (``method``) runs imitation's AIRL tutorial (``docs/tutorials/4_train_airl``)
   the same way: PPO also with ``clip_range`` and ``vf_coef`` from the settings,
   ``BasicShapedRewardNet`` with ``RunningNorm`` (reward and potential hidden layers 32,
   32), ``AIRL`` with the settings' batch, buffer and discriminator steps;
3. evaluation: ``evaluate_policy`` greedy on ``eval_lanes`` vector envs seeded
   ``eval_seed`` (as imitation's own scripts evaluate), ``eval_episodes`` episodes.
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

from imitation.algorithms.adversarial.airl import AIRL  # noqa: E402
from imitation.algorithms.adversarial.gail import GAIL  # noqa: E402
from imitation.data import rollout  # noqa: E402
from imitation.data.wrappers import RolloutInfoWrapper  # noqa: E402
from imitation.rewards.reward_nets import BasicRewardNet, BasicShapedRewardNet  # noqa: E402
from imitation.util import logger as imit_logger  # noqa: E402
from imitation.util.networks import RunningNorm  # noqa: E402
from imitation.util.util import make_vec_env  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.ppo import MlpPolicy  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peer_run import ScriptedExpert, expert_function  # noqa: E402

T_IMPORTED = time.perf_counter()


def venv_of(env_id: str, lanes: int, seed: int):
    return make_vec_env(
        env_id,
        rng=np.random.default_rng(seed),
        n_envs=lanes,
        post_wrappers=[lambda env, _: RolloutInfoWrapper(env)],
    )


def run(spec: dict) -> dict:
    now = time.perf_counter
    seed, env_id, lanes, s = spec["seed"], spec["env_id"], spec["lanes"], spec["settings"]
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    quiet = imit_logger.configure(tempfile.mkdtemp(prefix="peer-gail-log-"), [])

    t0 = now()
    venv = venv_of(env_id, lanes, seed)
    expert = ScriptedExpert(venv.observation_space, venv.action_space, expert_function(env_id))
    demos = rollout.rollout(
        expert,
        venv,
        rollout.make_sample_until(min_timesteps=None, min_episodes=spec["demo_episodes"]),
        rng=rng,
        deterministic_policy=True,
    )[: spec["demo_episodes"]]
    airl = spec["method"] == "airl"
    tutorial = {"clip_range": s["clip_epsilon"], "vf_coef": s["vf_coef"]} if airl else {}
    learner = PPO(
        env=venv,
        policy=MlpPolicy,
        batch_size=s["minibatch_size"],
        ent_coef=0.0,
        learning_rate=s["lr"],
        gamma=s["gamma"],
        n_epochs=s["ppo_epochs"],
        n_steps=spec["rollout_steps"] // lanes,
        seed=seed,
        device="cpu",
        **tutorial,
    )
    reward_net = (BasicShapedRewardNet if airl else BasicRewardNet)(
        observation_space=venv.observation_space,
        action_space=venv.action_space,
        normalize_input_layer=RunningNorm,
    )
    trainer = (AIRL if airl else GAIL)(
        demonstrations=demos,
        demo_batch_size=s["discriminator_batch"],
        gen_replay_buffer_capacity=s["gen_replay_buffer_capacity"],
        n_disc_updates_per_round=s["discriminator_updates"],
        venv=venv,
        gen_algo=learner,
        reward_net=reward_net,
        allow_variable_horizon=env_id == "CartPole-v1",
        custom_logger=quiet,
    )
    setup = now() - t0

    t0 = now()
    trainer.train(spec["total_steps"])
    train = now() - t0

    t0 = now()
    eval_venv = venv_of(env_id, spec["eval_lanes"], spec["eval_seed"])
    eval_venv.seed(spec["eval_seed"])
    rewards, _ = evaluate_policy(
        learner,
        eval_venv,
        n_eval_episodes=spec["eval_episodes"],
        deterministic=True,
        return_episode_rewards=True,
        warn=False,
    )
    evaluation = now() - t0
    return {
        "library": "imitation",
        "phases": {
            "imports": T_IMPORTED - T_START,
            "setup": setup,
            "train": train,
            "evaluation": evaluation,
        },
        "returns": {"final": float(np.mean(rewards))},
        "env_steps": int(learner.num_timesteps),
        "demo_rows": int(sum(len(t) for t in demos)),
    }


def main() -> None:
    out = run(json.loads(sys.argv[1]))
    out["phases"]["in_process"] = time.perf_counter() - T_START
    Path(sys.argv[2]).write_text(json.dumps(out))


if __name__ == "__main__":
    main()

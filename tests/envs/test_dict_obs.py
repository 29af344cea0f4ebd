"""Envs with a gymnasium Dict observation (gym-pusht's ``pixels_agent_pos``), mapped onto the
key vocabulary as LeRobot names the entries (issue item 6).

The envs are registered here, at import, so that ``parallel=True`` workers (fresh
processes) find them through ``"tests.envs.test_dict_obs:<id>"``.
"""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms.bc import BCConfig, fit_bc
from imitrl.datasets import load_lerobot, save_lerobot
from imitrl.envs import make_env
from imitrl.envs.dict_obs import ENVIRONMENT_STATE
from imitrl.evaluation.evaluate import evaluate
from imitrl.learners import build

torch.set_num_threads(1)

SIDE = 16  # image side, pixels
LIMIT = 20  # steps per episode
SMALL = {"channels": (8, 8), "hidden": (32,)}  # fast on 2 CPU cores


def draw(pos: np.ndarray, side: int = SIDE) -> np.ndarray:
    """uint8 ``[side, side, 3]``: a white 3x3 dot where ``pos`` (in [-1, 1]^2) lies."""
    image = np.zeros((side, side, 3), dtype=np.uint8)
    r, c = np.clip(((np.asarray(pos) + 1) / 2 * (side - 1)).round().astype(int), 1, side - 2)
    image[r - 1 : r + 2, c - 1 : c + 2] = 255
    return image


class DotPush(gym.Env):
    """Push a dot to the origin: ``{"pixels": uint8 [16, 16, 3], "agent_pos": float64 [2]}``
    (gym-pusht's ``pixels_agent_pos`` layout), action ``[2]`` in [-1, 1], reward -|pos|.

    ``cameras``: ``pixels`` is a Dict of two cameras (``top`` draws the dot, ``wrist`` is
    an 8x8 crop); ``state``: an ``environment_state`` [4] entry; ``extra``: an entry with
    no imitrl key (``achieved_goal``)."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, cameras=False, state=False, extra=False, render_mode=None):
        self.render_mode = render_mode
        image = gym.spaces.Box(0, 255, (SIDE, SIDE, 3), np.uint8)
        pixels = (
            gym.spaces.Dict({"top": image, "wrist": gym.spaces.Box(0, 255, (8, 8, 3), np.uint8)})
            if cameras
            else image
        )
        entries = {"pixels": pixels, "agent_pos": gym.spaces.Box(-1.0, 1.0, (2,), np.float64)}
        if state:
            entries["environment_state"] = gym.spaces.Box(-2.0, 2.0, (4,), np.float64)
        if extra:
            entries["achieved_goal"] = gym.spaces.Box(-1.0, 1.0, (2,), np.float64)
        self.observation_space = gym.spaces.Dict(entries)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.cameras, self.state, self.extra = cameras, state, extra

    def _obs(self) -> dict:
        top = draw(self.pos)
        obs = {"pixels": {"top": top, "wrist": top[4:12, 4:12]} if self.cameras else top}
        obs["agent_pos"] = self.pos.copy()
        if self.state:
            obs["environment_state"] = np.concatenate([self.pos, -self.pos])
        if self.extra:
            obs["achieved_goal"] = self.pos.copy()
        return obs

    def render(self):
        return draw(self.pos)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.np_random.uniform(-1.0, 1.0, size=2)
        return self._obs(), {}

    def step(self, action):
        self.pos = np.clip(self.pos + 0.25 * np.clip(action, -1, 1), -1.0, 1.0)
        return self._obs(), -float(np.linalg.norm(self.pos)), False, False, {}


def _expert(pos: np.ndarray) -> np.ndarray:
    return np.clip(-2.0 * pos, -1.0, 1.0).astype(np.float32)


MODULE = "tests.envs.test_dict_obs"
ONE = "imitrl-test/DotPush-v0"
CAMERAS = "imitrl-test/DotPushCameras-v0"
STATE = "imitrl-test/DotPushState-v0"
EXTRA = "imitrl-test/DotPushExtra-v0"
for _id, _kwargs in (
    (ONE, {}),
    (CAMERAS, {"cameras": True}),
    (STATE, {"state": True}),
    (EXTRA, {"extra": True}),
):
    if _id not in gym.registry:
        gym.register(_id, entry_point=DotPush, kwargs=_kwargs, max_episode_steps=LIMIT)


def _keys(env) -> dict:
    spec = env.observation_spec
    return {k: (spec[k].dtype, tuple(spec[k].shape)) for k in spec.keys(True, True)}


# ------------------------------------------------------------------ mapping
@pytest.mark.parametrize(("num_envs", "parallel"), [(1, False), (3, False), (2, True)])
def test_a_dict_observation_is_renamed_as_lerobot_names_its_entries(num_envs, parallel):
    env = make_env(f"{MODULE}:{ONE}", seed=0, num_envs=num_envs, parallel=parallel)
    batch = () if num_envs == 1 and not parallel else (num_envs,)
    assert _keys(env) == {
        keys.OBSERVATION: (torch.float32, (*batch, 2)),
        keys.PIXELS: (torch.uint8, (*batch, SIDE, SIDE, 3)),
    }
    rows = env.rollout(LIMIT + 5, break_when_any_done=False)
    obs, pixels = rows.get(keys.OBSERVATION), rows.get(keys.PIXELS)
    assert obs.dtype == torch.float32 and pixels.dtype == torch.uint8
    # each image is the one the env drew from that very state: the entries are not swapped
    flat_obs, flat_pix = obs.reshape(-1, 2), pixels.reshape(-1, SIDE, SIDE, 3)
    for o, p in zip(flat_obs, flat_pix, strict=True):
        assert np.array_equal(draw(o.double().numpy()), p.numpy())
    assert bool(rows.get(("next", "truncated")).any())  # the time limit ends episodes
    env.close()


def test_a_dict_of_cameras_nests_under_pixels_and_environment_state_keeps_its_name():
    env = make_env(CAMERAS, seed=0, num_envs=2)
    assert _keys(env) == {
        keys.OBSERVATION: (torch.float32, (2, 2)),
        (keys.PIXELS, "top"): (torch.uint8, (2, SIDE, SIDE, 3)),
        (keys.PIXELS, "wrist"): (torch.uint8, (2, 8, 8, 3)),
    }
    learner = build("for_env", env, pixel_key=(keys.PIXELS, "top"), **SMALL)
    assert learner.policy.in_keys == [(keys.PIXELS, "top")]
    assert np.isfinite(evaluate(env, learner, 2, seed=0).mean_return)

    env = make_env(STATE, seed=0)
    assert _keys(env)[ENVIRONMENT_STATE] == (torch.float32, (4,))
    td = env.reset()
    assert torch.equal(td.get(ENVIRONMENT_STATE)[:2], td.get(keys.OBSERVATION))


def test_dict_observations_imitrl_cannot_map_are_refused_naming_the_entry():
    with pytest.raises(ValueError, match=r"\['achieved_goal'\] have no imitrl key.*agent_pos"):
        make_env(EXTRA, seed=0)
    with pytest.raises(ValueError, match=r"\['achieved_goal'\] have no imitrl key"):
        make_env(EXTRA, seed=0, num_envs=2)
    with pytest.raises(ValueError, match="already holds 'pixels'"):
        make_env(ONE, seed=0, pixels=(8, 8))

    class Odd(gym.Env):
        def __init__(self, entries):
            self.observation_space = gym.spaces.Dict(entries)
            self.action_space = gym.spaces.Discrete(2)

    image = gym.spaces.Box(0, 255, (8, 8, 3), np.uint8)
    bad = {
        "float images": (
            {"pixels": gym.spaces.Box(0.0, 1.0, (8, 8, 3), np.float32)},
            r"'pixels' must be a uint8 image Box \[H, W, 3\]",
        ),
        "a 2-D state": (
            {"agent_pos": gym.spaces.Box(-1.0, 1.0, (2, 2))},
            r"'agent_pos' must be a numeric vector Box \[d\]",
        ),
        "a dotted camera": (
            {"pixels": gym.spaces.Dict({"cam.left": image})},
            r"camera name 'cam.left'",
        ),
        "nothing a learner reads": (
            {"environment_state": gym.spaces.Box(-1.0, 1.0, (3,))},
            r"needs 'agent_pos'.*or 'pixels'",
        ),
    }
    for name, (entries, match) in bad.items():
        gym.register(f"imitrl-test/Odd{len(name)}-v0", entry_point=Odd, kwargs={"entries": entries})
        with pytest.raises(ValueError, match=match):
            make_env(f"imitrl-test/Odd{len(name)}-v0", seed=0)


# ------------------------------------------------------- LeRobot data -> Dict env
def _record(episodes: int, seed: int) -> TensorDict:
    """Demonstrations recorded straight from gymnasium, one row per step as LeRobot's
    recorder stores them: ``agent_pos`` as the state, ``pixels`` as the image."""
    env = gym.make(ONE)
    columns: dict[str, list] = {k: [] for k in ("obs", "pix", "act", "rew", "end", "ep", "t")}
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        for t in range(LIMIT):
            action = _expert(obs["agent_pos"])
            columns["obs"].append(obs["agent_pos"].astype(np.float32))
            columns["pix"].append(obs["pixels"])
            columns["act"].append(action)
            obs, reward, _, truncated, _ = env.step(action)
            columns["rew"].append([reward])
            columns["end"].append([truncated])
            columns["ep"].append(e)
            columns["t"].append(t)
    n = len(columns["t"])
    truncated = torch.tensor(np.array(columns["end"]))
    action = torch.tensor(np.array(columns["act"]))
    return TensorDict(
        {
            keys.OBSERVATION: torch.tensor(np.array(columns["obs"])),
            keys.PIXELS: torch.tensor(np.array(columns["pix"])),
            keys.EXPERT_ACTION: action,
            keys.EPISODE: torch.tensor(columns["ep"]),
            keys.STEP: torch.tensor(columns["t"]),
            keys.NEXT: {
                keys.REWARD: torch.tensor(columns["rew"], dtype=torch.float32),
                keys.DONE: truncated,
                keys.TERMINATED: torch.zeros_like(truncated),
                keys.TRUNCATED: truncated,
            },
        },
        [n],
    )


def test_bc_on_a_lerobot_dataset_evaluates_in_the_matching_dict_env(tmp_path):
    path = save_lerobot(_record(8, seed=100), tmp_path / "dotpush", fps=10)
    features = json.loads((path / "meta" / "info.json").read_text())["features"]
    assert {"observation.state", "observation.image", "action"} <= set(features)
    rows = load_lerobot(path, images="load").rows

    env = make_env(ONE, seed=0)  # no key mapping anywhere: the keys already agree
    for key in (keys.OBSERVATION, keys.PIXELS):
        assert rows.get(key).dtype == env.observation_spec[key].dtype
        assert rows.get(key).shape[1:] == env.observation_spec[key].shape
    learner = build("for_env", env, state=True, head="deterministic", loss="mse", **SMALL)
    assert learner.policy.in_keys == [keys.PIXELS, keys.OBSERVATION]
    fit_bc(learner, rows, BCConfig(num_steps=300, batch_size=64))

    # evaluated in the Dict env, single and vectorised: it pushes the dot home
    clone = evaluate(env, learner, 8, seed=1000).mean_return
    lanes = make_env(ONE, seed=0, num_envs=2)
    assert evaluate(lanes, learner, 8, seed=1000).mean_return > -10.0

    # the do-nothing baseline: the dot stays where it starts
    still = TensorDictModule(
        lambda obs: torch.zeros(*obs.shape[:-1], 2), [keys.OBSERVATION], [keys.ACTION]
    )
    idle = evaluate(env, still, 8, seed=1000, exploration=ExplorationType.DETERMINISTIC)
    assert clone > idle.mean_return + 5.0, (clone, idle.mean_return)

"""Meta-World pixels under LeRobot's observation contract (issue 46): with the default
settings, ``metaworld/<task>`` with ``obs_type=pixels_agent_pos`` gives the frames LeRobot's
``MetaworldEnv`` gives, byte for byte, at every step of an episode.

The reference is recorded with metaworld alone, called as LeRobot's env calls it
(lerobot ``src/lerobot/envs/metaworld.py``: ``MT1(task, seed=42)``, the task class with
``render_mode="rgb_array"`` and the ``corner2`` camera moved to ``(0.75, 0.075, 0.7)``,
``set_task(train_tasks[0])``, one reset, ``_freeze_rand_vec = False``, then
``reset(seed=)`` and steps, each frame flipped on both axes; the episode's variation drawn
from metaworld's seeded generator, as imitrl's env draws it). It is recorded live, on this
machine's renderer, and its SHA-256 digests are also committed
(``metaworld_frames.json``, written by ``python tests/envs/test_metaworld_frames.py``,
with the OpenGL renderer that drew them), which a recording on that renderer must
reproduce.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

TASK, SEED, STEPS = "reach-v3", 7, 6
FIXTURE = Path(__file__).with_name("metaworld_frames.json")


def lerobots_frames(task: str = TASK, seed: int = SEED, steps: int = STEPS):
    """Frames, the actions taken (metaworld's scripted policy's, on the state) and the
    renderer that drew them, of one episode, metaworld alone as LeRobot's env drives it."""
    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = "egl"
    import metaworld
    import metaworld.policies as policies

    mt1 = metaworld.MT1(task, seed=42)
    env = mt1.train_classes[task](render_mode="rgb_array", camera_name="corner2")
    env.set_task(mt1.train_tasks[0])
    env.model.cam_pos[2] = [0.75, 0.075, 0.7]
    env.reset()
    env._freeze_rand_vec = False
    # LeRobot's reset(seed=) is ignored by metaworld (the variation comes from numpy's
    # global generator there); the variation is drawn from metaworld's own seeded
    # generator instead, so both sides render the same scene
    env.seeded_rand_vec = True
    env.seed(seed)
    policy = policies.SawyerReachV3Policy()
    obs, _ = env.reset(seed=seed)
    frames, actions = [np.flip(env.render(), (0, 1)).copy()], []
    drawn_by = _renderer()  # the env's context is current after its first frame
    for _ in range(steps):
        action = np.clip(policy.get_action(obs), -1, 1).astype(np.float32)
        obs, *_ = env.step(action)
        frames.append(np.flip(env.render(), (0, 1)).copy())
        actions.append(action)
    env.close()
    return frames, actions, drawn_by


def _renderer() -> str:
    """The OpenGL renderer and version of the current context (llvmpipe names its LLVM
    and its vector width: what decides the bytes)."""
    from OpenGL import GL

    return f"{GL.glGetString(GL.GL_RENDERER).decode()}; {GL.glGetString(GL.GL_VERSION).decode()}"


def _digest(frame: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(frame).tobytes()).hexdigest()


@pytest.fixture(scope="module")
def reference():
    pytest.importorskip("metaworld")
    for _ in range(3):  # a blank frame is a failed draw (seen once under a loaded suite)
        try:
            recorded = lerobots_frames()
        except Exception as err:  # no OpenGL backend on this machine (EGL or OSMesa)
            pytest.skip(f"metaworld cannot render here: {err}")
        if not any(not frame.any() for frame in recorded[0]):
            return recorded
    pytest.fail("metaworld alone drew a blank frame in 3 recordings of the same episode")


def _imitrls_frames(actions, **kwargs) -> list[np.ndarray]:
    """The pixels of ``metaworld/<task>`` (the id ``make_env`` builds: its default settings) reset with ``SEED``
    and stepped with ``actions``."""
    import gymnasium

    import imitrl.envs.metaworld  # noqa: F401  (registers metaworld/<task>)

    env = gymnasium.make(f"metaworld/{TASK}", obs_type="pixels_agent_pos", **kwargs)
    obs, _ = env.reset(seed=SEED)
    got = [obs["pixels"]]
    for action in actions:
        obs, *_ = env.step(action)
        got.append(obs["pixels"])
    env.close()
    return got


def test_default_pixels_are_lerobots_frames_byte_for_byte(reference):
    frames, actions, _ = reference
    got = _imitrls_frames(actions)
    assert len(got) == len(frames) == STEPS + 1
    for step, (a, b) in enumerate(zip(got, frames)):
        assert a.shape == b.shape == (480, 480, 3) and a.dtype == b.dtype == np.uint8
        assert np.array_equal(a, b), (step, float(np.abs(a.astype(int) - b).mean()))


def test_the_recording_reproduces_the_committed_digests(reference):
    """On the renderer that recorded them, bit for bit; another renderer (another LLVM,
    another vector width) may draw other bytes, and the live comparison above is then
    the check."""
    recorded = json.loads(FIXTURE.read_text())
    assert (recorded["task"], recorded["seed"]) == (TASK, SEED)
    here = reference[2]
    if here != recorded["renderer"]:
        pytest.skip(f"frames drawn by {here}, the digests by {recorded['renderer']}")
    assert [_digest(f) for f in reference[0]] == recorded["sha256"]


def test_fast_render_is_asked_for_and_changes_the_frames(reference):
    frames, actions, _ = reference
    got = _imitrls_frames(actions[:1], fast_render=True)
    assert not np.array_equal(got[1], frames[1])  # shadows off: not LeRobot's frames


if __name__ == "__main__":  # re-record the digests (metaworld alone)
    frames, _, drawn_by = lerobots_frames()
    digests = [_digest(f) for f in frames]
    record = {"task": TASK, "seed": SEED, "renderer": drawn_by, "sha256": digests}
    FIXTURE.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {FIXTURE} ({len(frames)} frames)", file=sys.stderr)

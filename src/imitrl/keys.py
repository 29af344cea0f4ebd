"""The tensordict key vocabulary of imitrl: one place that names every key.

Keys are the API. Modules declare which of these they read and write; an expert's
label never lives under a key a learner writes, so running a learner on a batch of
demonstrations can never overwrite the labels it is trained on.

Per-transition keys (root of a rollout / demonstration row):

========================  ==========================================================
``OBSERVATION``           what the policy sees at step t (env's observation key); in a
                          pixel env, the state (a privileged expert reads it)
``PIXELS``                uint8 ``[H, W, C]`` camera image at step t (TorchRL's and
                          LeRobot's layout; C = 3 per stacked frame): one camera as
                          ``"pixels"``, several as nested keys ``("pixels", name)``
                          (LeRobot's ``observation.images.<name>``; a pixel learner
                          reads the one its ``pixel_key`` names)
``ENVIRONMENT_STATE``     a robot env's ``environment_state`` at step t (float32; what
                          LeRobot records as ``observation.environment_state``)
``ACTION``                the action executed in the env at step t
``EXPERT_ACTION``         the expert's label for the state at step t (never written
                          by a learner)
``LEARNER_ACTION``        the learner's own proposal at step t (kept by the DAgger
                          mixture before it decides which action is executed)
``EXPERT_EXECUTED``       bool: the executed action was the expert's
``EXPERT_PLAN``           ``[H, *action]``: the expert's own next H actions from the
                          row's state, played on the simulator from there and undone
                          (chunk-aware DAgger); past its episode's end, its last one
``EXPERT_PLAN_PAD``       bool ``[H]``: the plan entry lies past the episode's end
``EPISODE``               int64 episode id, unique within a buffer
``ROUND``                 int64 DAgger round that collected the row (0 = offline demos)
``BETA``                  float: the probability that the round's behaviour policy
                          executed the expert's action (1 in round 0; -1 where a gate,
                          not a coin, decided); a LeRobot dataset of DAgger rounds
                          carries it per frame (``imitrl.beta``)
``POLICY_VERSION``        int64: the fit whose learner acted (round r's rows: fit r - 1;
                          -1: no learner acted, an expert or a recording); a LeRobot
                          dataset of DAgger rounds carries it (``imitrl.policy_version``)
``STEP``                  int64 time index of the row inside its episode
``WEIGHT``                float per-row weight of the log-likelihood (advantage);
                          treated as data, never differentiated
``LOGITS``                categorical policy head output
``LOC`` / ``SCALE``       Gaussian policy head outputs
``STATE_VALUE``           value head output
``POLICY_NOISE``          float ``[*B, d]``: the starting noise a generative policy
                          (flow) samples from, when its caller holds it (a chunked
                          policy holding one draw per episode); absent: drawn afresh
========================  ==========================================================

A demonstration row carries ``OBSERVATION``, a ``PIXELS`` key, or both (a camera-only
dataset has no ``OBSERVATION``; :data:`imitrl.data.OBSERVATION_KEYS`).

Keys under ``"next"`` follow TorchRL: ``("next", "reward")``, ``("next", "done")``,
``("next", "terminated")``, ``("next", "truncated")``, ``("next", OBSERVATION)``.
"""

from __future__ import annotations

OBSERVATION = "observation"
PIXELS = "pixels"
ENVIRONMENT_STATE = "environment_state"
ACTION = "action"
EXPERT_ACTION = "expert_action"
LEARNER_ACTION = "learner_action"
EXPERT_EXECUTED = "expert_executed"
EXPERT_PLAN = "expert_plan"
EXPERT_PLAN_PAD = "expert_plan_is_pad"
EPISODE = "episode"
ROUND = "round"
BETA = "beta"
POLICY_VERSION = "policy_version"
STEP = "step"
WEIGHT = "weight"
LOGITS = "logits"
LOC = "loc"
SCALE = "scale"
STATE_VALUE = "state_value"
POLICY_NOISE = "policy_noise"

NEXT = "next"
REWARD = "reward"
DONE = "done"
TERMINATED = "terminated"
TRUNCATED = "truncated"

__all__ = [
    "ACTION",
    "BETA",
    "DONE",
    "ENVIRONMENT_STATE",
    "EPISODE",
    "EXPERT_ACTION",
    "EXPERT_EXECUTED",
    "EXPERT_PLAN",
    "EXPERT_PLAN_PAD",
    "LEARNER_ACTION",
    "LOC",
    "LOGITS",
    "NEXT",
    "OBSERVATION",
    "PIXELS",
    "POLICY_NOISE",
    "POLICY_VERSION",
    "REWARD",
    "ROUND",
    "SCALE",
    "STATE_VALUE",
    "STEP",
    "TERMINATED",
    "TRUNCATED",
    "WEIGHT",
]

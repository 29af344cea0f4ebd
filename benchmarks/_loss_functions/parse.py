"""A task from the command line: ``loss_functions.py --task key=value,...`` -> a
:class:`~_loss_functions.tasks.TaskDef` on the default budget, each key overriding its part."""

from __future__ import annotations

from dataclasses import fields, replace

from _loss_functions.tasks import _WIDE, Protocol, TaskDef
from imitrl.algorithms import BCConfig

_PROTOCOL_KEYS = {
    "demos": "demo_episodes",
    "rounds": "rounds",
    "episodes": "episodes_per_round",
    "eval": "eval_episodes",
    "max_episode_steps": "max_episode_steps",
    "round_steps": "round_steps",
}
_DEFAULT = Protocol(5, 4, 2, BCConfig(num_steps=2000, batch_size=256), _WIDE, 10)


def parse_task(text: str) -> TaskDef:
    """``--task key=value,...`` -> a :class:`TaskDef`.

    Keys: ``name``, ``env`` (required); ``expert``, ``expert_kind``, ``dataset``,
    ``score``, ``max_steps``, ``probe``, ``outcome`` (the fields of TaskDef); the budget
    ``demos``, ``rounds``, ``episodes``, ``eval``, ``max_episode_steps``, ``steps`` (fit
    steps), ``round_steps`` (warm-started relabel rounds, :attr:`Protocol.round_steps`),
    ``batch``, ``hidden`` (e.g. ``128x128``), ``lr``. Unset budget entries take ``5``
    demos, 4 rounds (1 without an expert), 2 episodes per round, 2000 steps x 256 (each
    round refits), 128x128, lr 3e-3, 10 evaluation episodes.
    """
    pairs: dict[str, str] = {}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise ValueError(f"--task {text!r}: expected key=value pairs separated by commas")
        pairs[key.strip()] = value.strip()
    known = {f.name for f in fields(TaskDef)} - {"protocol"}
    extra = {"steps", "batch", "hidden", "lr", *_PROTOCOL_KEYS}
    unknown = set(pairs) - known - extra
    if unknown:
        raise ValueError(f"--task: unknown keys {sorted(unknown)}; known: {sorted(known | extra)}")
    if "name" not in pairs or "env" not in pairs:
        raise ValueError(f"--task {text!r}: name= and env= are required")
    protocol = _DEFAULT
    if "expert" not in pairs:
        protocol = replace(protocol, rounds=1)
    ints = {k: int(pairs[k]) for k in _PROTOCOL_KEYS if k in pairs}
    protocol = replace(protocol, **{_PROTOCOL_KEYS[k]: v for k, v in ints.items()})
    bc, learner = protocol.bc, protocol.learner
    if "steps" in pairs:
        bc = replace(bc, num_steps=int(pairs["steps"]))
    if "batch" in pairs:
        bc = replace(bc, batch_size=int(pairs["batch"]))
    if "hidden" in pairs:
        learner = replace(learner, hidden=tuple(int(h) for h in pairs["hidden"].split("x")))
    if "lr" in pairs:
        learner = replace(learner, lr=float(pairs["lr"]))
    protocol = replace(protocol, bc=bc, learner=learner)
    own = {k: v for k, v in pairs.items() if k in known}
    if "max_steps" in own:
        own["max_steps"] = int(own["max_steps"])
    return TaskDef(**own, protocol=protocol)

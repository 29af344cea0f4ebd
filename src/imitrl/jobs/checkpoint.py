"""A run's files: ``config.json`` + ``learner.pt`` (the checkpoint) and ``results.json``.

The checkpoint is the job's config (enough to rebuild the learner: env, loss,
hidden sizes, learning rate, seed) and ``torch.save(learner.state_dict())`` (the
weights and the observation normaliser's statistics). ``imitrl eval --checkpoint
DIR`` rebuilds the learner from the config and loads the weights.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import torch
from torchrl.envs import EnvBase

from imitrl.jobs.resolve import FOR_ENV, LEGACY_DEFAULT, builds_table, learner_factory
from imitrl.objectives import registry
from imitrl.policies import Learner

__all__ = [
    "CONFIG_FILE",
    "RESULTS_FILE",
    "WEIGHTS_FILE",
    "checkpoint_env",
    "load_learner",
    "read_config",
    "save_run",
    "to_json",
]

CONFIG_FILE, WEIGHTS_FILE, RESULTS_FILE = "config.json", "learner.pt", "results.json"


def to_json(value: Any) -> Any:
    """Dataclasses, paths and tuples as plain JSON values."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def save_run(out: Path, command: str, config: Any, learner: Learner, results: dict) -> None:
    """Write ``config.json``, ``learner.pt`` and ``results.json`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    meta = {"command": command, "config": to_json(config)}
    (out / CONFIG_FILE).write_text(json.dumps(meta, indent=2) + "\n")
    torch.save(learner.state_dict(), out / WEIGHTS_FILE)
    (out / RESULTS_FILE).write_text(json.dumps(to_json(results), indent=2) + "\n")


MAX_WIDTH = 1 << 16
"""widest hidden layer a checkpoint's config may ask for (a downloaded config is hostile:
it never makes ``imitrl eval`` allocate what it likes)"""


def read_config(checkpoint: Path) -> dict:
    """The saved job config (a dict of the ``bc`` / ``dagger`` flags), its fields checked
    (a downloaded checkpoint is hostile until checked: :func:`_check_fields`)."""
    path = Path(checkpoint) / CONFIG_FILE
    if not path.is_file() or not (Path(checkpoint) / WEIGHTS_FILE).is_file():
        raise ValueError(
            f"--checkpoint {checkpoint}: expected {CONFIG_FILE} and {WEIGHTS_FILE} "
            "(the --out directory of imitrl bc or imitrl dagger)"
        )
    try:
        config = json.loads(path.read_text())["config"]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a config written by imitrl bc/dagger ({err})") from err
    _check_fields(path, config)
    return config


def _check_fields(path: Path, config: Any) -> None:
    """The fields ``imitrl eval`` rebuilds a learner from: what imitrl bc/dagger write."""
    if not isinstance(config, dict):
        raise ValueError(f"{path}: 'config' must be an object, got {type(config).__name__}")

    def bad(field: str, expected: str) -> ValueError:
        return ValueError(f"{path}: {field} must be {expected}, got {config.get(field)!r}")

    for field in ("env", "loss"):
        if not isinstance(config.get(field), str) or not config[field]:
            raise bad(field, "a name")
    hidden = config.get("hidden")  # null: the network's own layers (no --hidden given)
    if hidden is not None and (
        not isinstance(hidden, list)
        or not all(type(h) is int and 1 <= h <= MAX_WIDTH for h in hidden)
    ):
        raise bad("hidden", f"a list of layer widths in [1, {MAX_WIDTH}] or null")
    if type(config.get("seed")) is not int:
        raise bad("seed", "an integer")
    lr = config.get("lr")  # null: the loss's own rate (no --lr given)
    if lr is not None and (
        isinstance(lr, bool) or not isinstance(lr, int | float) or not 0 < lr < float("inf")
    ):
        raise bad("lr", "a positive number or null")
    steps = config.get("max_episode_steps")
    if steps is not None and (type(steps) is not int or steps < 1):
        raise bad("max_episode_steps", "a positive integer or null")
    pairs = config.get("env_kwargs", [])
    if not isinstance(pairs, list) or not all(_plain_pair(p) for p in pairs):
        raise bad("env_kwargs", "a list of [name, value] pairs of JSON scalars (or lists of them)")


def _plain_pair(pair: Any) -> bool:
    """``[name, value]``: a keyword name and a JSON scalar (data, never an object to build)."""
    return (
        isinstance(pair, list)
        and len(pair) == 2
        and isinstance(pair[0], str)
        and pair[0].isidentifier()
        and (_scalar(pair[1]) or (isinstance(pair[1], list) and all(map(_scalar, pair[1]))))
    )


def _scalar(value: Any) -> bool:
    return value is None or isinstance(value, str | int | float | bool)


def checkpoint_env_kwargs(config: dict) -> dict:
    """The env's constructor arguments a checkpoint was trained with (checked data)."""
    return {name: value for name, value in config.get("env_kwargs", [])}


def checkpoint_env(checkpoint: Path, config: dict) -> str:
    """The env id a checkpoint was trained on, when it names no code to import.

    An id of the form ``module:Env-v0`` imports ``module`` to register the env; a
    checkpoint is data, and loading it never runs code the user did not name, so such an
    id must come from the command line (``--env``) instead (ValueError saying so)."""
    env = config["env"]
    if ":" in env:
        module = env.split(":", 1)[0]
        raise ValueError(
            f"{Path(checkpoint) / CONFIG_FILE} names env {env!r}, which would import the "
            f"module {module!r}; imitrl never imports code a checkpoint names. If you trust "
            f"that module, name it yourself: --env {env}"
        )
    return env


def _saved_lr(config: dict) -> float | None:
    """The learning rate to rebuild a saved learner with: the one it trained at, except
    for an entry that trains at its recipe's own (a run saved before such entries refused
    --lr recorded the CLI default, which they did not use)."""
    loss = config["loss"]
    if loss in registry.names() and registry.get(loss).own_lr is not None:
        return None
    return config.get("lr")


def load_learner(checkpoint: Path, env: EnvBase, *, device: str | None = None) -> Learner:
    """The learner saved in ``checkpoint``, rebuilt for ``env`` on ``device`` (None: the
    CPU; the checkpoint may have been saved on another device) and loaded with its weights."""
    config = read_config(checkpoint)
    loss = config["loss"]
    loss = FOR_ENV if loss == LEGACY_DEFAULT else loss  # saved when default meant for_env
    hidden = None if config["hidden"] is None else tuple(config["hidden"])
    if hidden is not None and builds_table(loss, env):
        hidden = None  # a table: runs before --hidden was optional recorded the default
    make = learner_factory(
        loss,
        env,
        hidden=hidden,
        lr=_saved_lr(config),
        seed=config["seed"],
        device=device,
    )
    learner = make()
    where = Path(checkpoint) / WEIGHTS_FILE
    try:  # onto the CPU first: a GPU checkpoint loads on a machine without one
        state = torch.load(where, weights_only=True, map_location="cpu")
    except Exception as err:  # torch.load raises assorted errors on a bad archive
        raise ValueError(
            f"{where}: not a learner's weights ({type(err).__name__}: {err})"
        ) from None
    try:
        learner.load_state_dict(state)
    except RuntimeError as err:  # shapes or names that do not match the rebuilt learner
        raise ValueError(
            f"{checkpoint}: the weights do not fit the rebuilt learner on {learner.device} ({err})"
        ) from err
    return learner

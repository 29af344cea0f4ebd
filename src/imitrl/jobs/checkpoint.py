"""A run's files: ``config.json`` + ``learner.pt`` (the checkpoint) and ``results.json``.

The checkpoint is the job's config (enough to rebuild the learner: env, loss,
hidden sizes, learning rate, seed) and ``torch.save(learner.state_dict())`` (the
weights and the observation normaliser's statistics). ``imitrl eval --checkpoint
DIR`` rebuilds the learner from the config and loads the weights.

A checkpoint may be downloaded, and replaced by a writer while it is read: it is hostile
until checked. :func:`read_checkpoint` reads both files from the folder pinned once, each
opened once by descriptor (a regular file inside the folder: no link out, no FIFO),
sizes bounded before anything is read; the saved config meets the checks of the flags it
came from (:mod:`imitrl.limits`: ``hidden: [65536, 65536]`` asks for more weights
than a network may have); the network it asks for must fit in the weights file before it
is built (:func:`build_learner`, :func:`check_holds`).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torchrl.envs import EnvBase

from imitrl.fs.files import replace_file
from imitrl.fs.reading import (
    OpenedFolder,
    ReplacedWhileReading,
    check_stored_zip,
    parse_json,
    read_whole,
)
from imitrl.jobs.configs import BCJob
from imitrl.jobs.resolve import FOR_ENV, LEGACY_DEFAULT, learner_factory
from imitrl.learners import Learner, TaskSpec, registry, resolve
from imitrl.limits import hidden_parameters

__all__ = [
    "CONFIG_FILE",
    "MAX_CONFIG_BYTES",
    "MAX_WEIGHTS_BYTES",
    "PARAMETER_BYTES",
    "RESULTS_FILE",
    "WEIGHTS_FILE",
    "SavedRun",
    "build_learner",
    "check_holds",
    "checkpoint_env",
    "checkpoint_env_kwargs",
    "load_learner",
    "read_checkpoint",
    "read_config",
    "save_checkpoint",
    "save_run",
    "saved_loss",
    "to_json",
]

CONFIG_FILE, WEIGHTS_FILE, RESULTS_FILE = "config.json", "learner.pt", "results.json"


def to_json(value: Any) -> Any:
    """Dataclasses, paths and tuples as plain JSON values; a NaN or infinite float as
    null, which JSON has for it (``--steps 0``'s final loss: a strict reader refused the
    ``NaN`` Python writes)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def save_checkpoint(out: Path, command: str, config: Any, learner: Learner) -> None:
    """Write ``config.json``, then ``learner.pt``, into ``out``, each whole
    (:func:`~imitrl.fs.files.replace_file`): the checkpoint. A job saves it as soon as the
    learner is fitted, before it evaluates it, so an evaluation that fails or is
    interrupted leaves the fit where :mod:`imitrl.fs.run_folder` keeps it."""
    out.mkdir(parents=True, exist_ok=True)
    meta = {"command": command, "config": to_json(config)}
    replace_file(out / CONFIG_FILE, json.dumps(meta, indent=2) + "\n")
    weights = io.BytesIO()
    torch.save(learner.state_dict(), weights)
    replace_file(out / WEIGHTS_FILE, weights.getvalue())


def save_run(
    out: Path,
    command: str,
    config: Any,
    learner: Learner,
    results: dict,
    *,
    saved: bool = False,
) -> None:
    """Write the checkpoint (:func:`save_checkpoint`), then ``results.json``: a run's
    last file, its mark of a finished run.

    ``saved``: the job saved the checkpoint when its fit ended, which stays as it is: the
    learner as fitted, before its evaluation drew from a sampling policy's own generator
    (:class:`~imitrl.rng.SavedGenerator`), so ``imitrl eval`` replays the run's evaluation."""
    if not saved:
        save_checkpoint(out, command, config, learner)
    replace_file(out / RESULTS_FILE, json.dumps(to_json(results), indent=2) + "\n")


MAX_CONFIG_BYTES = 1 << 20
"""largest ``config.json`` read (imitrl writes a few kB); a larger one is refused before
it is read"""
MAX_WEIGHTS_BYTES = 2 << 30
"""largest ``learner.pt`` loaded (2 GiB: the float32 weights of a policy and a value
network of :data:`~imitrl.limits.MAX_PARAMETERS` each are 800 MB); a larger one
is refused before it is read"""
PARAMETER_BYTES = 4
"""bytes a weight takes in ``learner.pt``: float32, what every imitrl learner holds"""


@dataclass(frozen=True)
class SavedRun:
    """A checkpoint read whole, from one folder (:func:`read_checkpoint`)."""

    path: Path
    """the checkpoint folder"""
    config: dict
    """the saved job config, its fields checked (:func:`read_config`)"""
    state: dict
    """``learner.state_dict()`` as saved, on the CPU"""
    weights_bytes: int
    """the size of ``learner.pt``, which the network the config asks for must fit"""


def _expect_checkpoint(checkpoint: Path) -> Path:
    """``checkpoint``, when it holds both files (ValueError saying what it should be)."""
    root = Path(checkpoint)
    if not (root / CONFIG_FILE).is_file() or not (root / WEIGHTS_FILE).is_file():
        raise ValueError(
            f"--checkpoint {checkpoint}: expected {CONFIG_FILE} and {WEIGHTS_FILE} "
            "(the --out directory of imitrl bc, dagger, gail or airl)"
        )
    return root


def read_config(checkpoint: Path) -> dict:
    """The saved job config (a dict of the ``bc`` / ``dagger`` flags), its fields checked
    (a downloaded checkpoint is hostile until checked: :func:`_check_fields`).

    ``config.json`` is opened once, by descriptor, inside the folder (no link out, no
    FIFO: :class:`~imitrl.fs.reading.OpenedFolder`), at most :data:`MAX_CONFIG_BYTES`.
    """
    root = _expect_checkpoint(checkpoint)
    return read_whole(root, _config, what="checkpoint", links=False)


def read_checkpoint(checkpoint: Path) -> SavedRun:
    """``config.json`` and ``learner.pt`` read together from the folder pinned once
    (:func:`~imitrl.fs.reading.read_whole`): both files of one checkpoint even while a
    writer replaces it (an exchange met while reading runs the read again on the new one;
    one met every time is :class:`~imitrl.fs.reading.ReplacedWhileReading`, "replaced
    while reading"). Before ``learner.pt`` is unpacked, its size is held to
    :data:`MAX_WEIGHTS_BYTES` and its records must be stored uncompressed (as
    ``torch.save`` writes them), so unpacking takes no more memory than the file's size;
    the network the config asks for is held to that size before it is built
    (:func:`build_learner`, :func:`check_holds`: the env's sizes count, and whether the
    widths are used at all).

    Raises:
        ValueError: naming the file and what is wrong with it.
    """
    root = _expect_checkpoint(checkpoint)
    return read_whole(root, _read_run, what="checkpoint", links=False)


def _read_run(folder: OpenedFolder) -> SavedRun:
    config = _config(folder)
    state, size = _weights(folder)
    if folder.replaced():  # files found by name (a hub snapshot's): both from one folder
        raise ReplacedWhileReading(f"{folder.root}: replaced while reading it")
    return SavedRun(folder.root, config, state, size)


def _config(folder: OpenedFolder) -> dict:
    """``config.json``'s ``config``, checked (:func:`_check_fields`)."""
    where = folder.root / CONFIG_FILE
    data = folder.read_bytes(CONFIG_FILE, named_by="checkpoint's config", limit=MAX_CONFIG_BYTES)
    meta = parse_json(data, where=str(where))
    if not isinstance(meta, dict) or "config" not in meta:
        raise ValueError(f"{where}: not a config written by imitrl bc/dagger (no 'config')")
    config = meta["config"]
    _check_fields(where, config)
    return config


def _weights(folder: OpenedFolder) -> tuple[dict, int]:
    """``learner.pt`` unpacked onto the CPU (a GPU checkpoint loads on a machine without
    one), once its size was checked; returns ``(state, size)``."""
    where = folder.root / WEIGHTS_FILE
    fd = folder.open(WEIGHTS_FILE, named_by="the checkpoint's layout")
    with os.fdopen(fd, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size > MAX_WEIGHTS_BYTES:
            raise ValueError(
                f"{where}: {size:_} bytes, more than the {MAX_WEIGHTS_BYTES:_} a learner's "
                "weights may take (imitrl.jobs.checkpoint.MAX_WEIGHTS_BYTES); refused "
                "before reading it"
            )
        check_stored_zip(f, where, size, what="a learner's weights")
        f.seek(0)
        try:
            state = torch.load(f, weights_only=True, map_location="cpu")
        except Exception as err:  # torch.load raises assorted errors on a bad archive
            raise ValueError(
                f"{where}: not a learner's weights ({type(err).__name__}: {err})"
            ) from None
    if not isinstance(state, dict):
        raise ValueError(f"{where}: not a learner's weights (a {type(state).__name__})")
    return state, size


def check_holds(where: Path, hidden: tuple[int, ...], size: int, env: EnvBase) -> None:
    """Refuse (ValueError naming both numbers) weights of ``size`` bytes too small for the
    network the hidden widths ask for on ``env``, before it is built: at least
    :func:`~imitrl.limits.hidden_parameters` weights of :data:`PARAMETER_BYTES` each,
    with the env's observation and action sizes."""
    inputs, outputs = _env_sizes(env)
    implied = hidden_parameters(tuple(hidden), inputs, outputs)
    if implied * PARAMETER_BYTES > size:
        raise ValueError(
            f"{where}: {size:_} bytes cannot hold the network its config asks for: hidden "
            f"{list(hidden)} on {inputs} inputs and {outputs} outputs has at least "
            f"{implied:_} weights, {implied * PARAMETER_BYTES:_} bytes as float32; "
            "refused before building it"
        )


def _env_sizes(env: EnvBase) -> tuple[int, int]:
    """The observation and action sizes an MLP on ``env`` reads and writes (1 and 1
    where the env is not one the registry describes: a lower bound for any network)."""
    task = TaskSpec.from_env(env)
    if not task.described:
        return 1, 1
    inputs = task.observation_dim if task.num_states is None else task.num_states
    assert inputs is not None  # a described task has one of the two (TaskSpec.observes)
    outputs = task.action if isinstance(task.action, int) else int(task.action.shape[0])
    return int(inputs), int(outputs)


def _builds_table(loss: str, env: EnvBase) -> bool:
    """Whether ``loss`` (resolved for ``env``) builds a logits table: an entry that does
    on integer states (``LossEntry.tables``), which has no hidden layers."""
    task = TaskSpec.from_env(env)
    name = resolve(loss, task)
    return name in registry.names() and registry.get(name).tables and task.num_states is not None


def _field_bound(name: str) -> Any:
    """The limits of ``BCJob``'s field ``name``: a saved config meets the checks the
    command line's flags meet (:mod:`imitrl.limits`)."""
    return next(f for f in dataclasses.fields(BCJob) if f.name == name).metadata["bound"]


def _check_fields(path: Path, config: Any) -> None:
    """The fields ``imitrl eval`` rebuilds a learner from: what imitrl bc/dagger write,
    held to the limits of their flags."""
    if not isinstance(config, dict):
        raise ValueError(f"{path}: 'config' must be an object, got {type(config).__name__}")
    for field in ("env", "loss"):
        if field == "env" and config.get(field, "") is None:
            continue  # imitrl bc --env none: trained on a dataset alone
        if not isinstance(config.get(field), str) or not config[field]:
            raise ValueError(f"{path}: {field} must be a name, got {config.get(field)!r}")
    # null hidden / lr / max_episode_steps: the network's own layers, the loss's own rate,
    # the env's own limit (no flag given)
    for field in ("hidden", "seed", "lr", "max_episode_steps"):
        _field_bound(field).check_field(config.get(field), f"{path}: {field}", none="null")
    for field in ("eval_episodes", "eval_seed"):  # null or missing: imitrl eval's defaults
        if config.get(field) is not None:
            _field_bound(field).check_field(config[field], f"{path}: {field}")
    pairs = config.get("env_kwargs", [])
    if not isinstance(pairs, list) or not all(_plain_pair(p) for p in pairs):
        raise ValueError(
            f"{path}: env_kwargs must be a list of [name, value] pairs of JSON scalars (or "
            f"lists of them, or lists of such lists), got {pairs!r}"[:300]
        )


def _names_a_path(text: str) -> bool:
    """Whether ``text`` could name a file outside a package's own folder: an absolute or
    home path, a path with a separator, or one relative to the working directory
    (``./``, ``../``). gymnasium's MuJoCo envs open ``xml_file`` so; a bare name
    (``"ant.xml"``) is looked up among gymnasium's own assets."""
    return (
        os.path.isabs(text)
        or text.startswith((".", "~"))
        or "/" in text
        or "\\" in text
        or "\0" in text
    )


def _plain_pair(pair: Any) -> bool:
    """``[name, value]``: a keyword name and plain JSON data (never an object to build)."""
    return (
        isinstance(pair, list)
        and len(pair) == 2
        and isinstance(pair[0], str)
        and pair[0].isidentifier()
        and _plain(pair[1], depth=2)
    )


def _plain(value: Any, depth: int) -> bool:
    """A JSON scalar, or a list of ``_plain`` values ``depth`` lists deep at most (a
    lake's ``desc``, rows of letters, is two: what ``--env-kwarg`` takes, a run saves)."""
    if isinstance(value, list):
        return depth > 0 and all(_plain(v, depth - 1) for v in value)
    return value is None or isinstance(value, str | int | float | bool)


def _leaves(value: Any) -> list:
    """The scalars of a ``_plain`` value."""
    return [x for v in value for x in _leaves(v)] if isinstance(value, list) else [value]


def checkpoint_env_kwargs(config: dict, checkpoint: str | Path, given: dict | None = None) -> dict:
    """The env's constructor arguments a checkpoint was trained with (checked data), with
    ``given`` (the command's ``--env-kwarg``) over them; ValueError for a saved one that
    names a file and that ``given`` does not replace (the env would open it: a checkpoint
    never makes imitrl read outside its folder; ``--env-kwarg`` names it)."""
    given = given or {}
    pairs = {name: value for name, value in config.get("env_kwargs", []) if name not in given}
    for name, value in pairs.items():
        for item in _leaves(value):
            if isinstance(item, str) and _names_a_path(item):
                raise ValueError(
                    f"{Path(checkpoint) / CONFIG_FILE}: env_kwargs {name}={item!r} names a "
                    "file, which the env would open; a checkpoint never makes imitrl read "
                    f"outside its folder. If you trust that file, name it yourself: "
                    f"--env-kwarg {name}={item}"[:400]
                )
    return {**pairs, **given}


def checkpoint_env(checkpoint: Path, config: dict) -> str:
    """The env id a checkpoint was trained on, when it names no code to import.

    An id of the form ``module:Env-v0`` imports ``module`` to register the env; a
    checkpoint is data, and loading it never runs code the user did not name, so such an
    id must come from the command line (``--env``) instead (ValueError saying so)."""
    env = config["env"]
    if env is None:
        raise ValueError(
            f"{Path(checkpoint) / CONFIG_FILE}: this learner was trained on a dataset alone "
            "(imitrl bc --env none): name the env to evaluate it in, --env ENV (its "
            "observations and actions must be the dataset's)"
        )
    if ":" in env:
        module = env.split(":", 1)[0]
        raise ValueError(
            f"{Path(checkpoint) / CONFIG_FILE} names env {env!r}, which would import the "
            f"module {module!r}; imitrl never imports code a checkpoint names. If you trust "
            f"that module, name it yourself: --env {env}"
        )
    return env


def saved_loss(checkpoint: Path, loss: str) -> str:
    """The registry name to rebuild a checkpoint's learner with: ``default`` saved when
    it meant ``for_env``; for a loss of the user's own, ``module:name``, ``name`` when it
    is registered in this process. imitrl never imports a module a checkpoint names:
    import it yourself (Python), or name it to ``imitrl eval --loss module:name``
    (ValueError saying so)."""
    if loss == LEGACY_DEFAULT:
        return FOR_ENV  # saved when default meant for_env
    if ":" not in loss:
        return loss
    module, _, name = loss.partition(":")
    if name not in registry.names():
        raise ValueError(
            f"{Path(checkpoint) / CONFIG_FILE} was trained with loss {loss!r}, which "
            f"importing the module {module!r} registers; imitrl never imports code a "
            f"checkpoint names. If you trust that module, name it yourself: --loss {loss} "
            f"(imitrl eval, imitrl compare), or import {module} before load_learner"
        )
    return name


def _saved_lr(config: dict, loss: str) -> float | None:
    """The learning rate to rebuild a saved learner of entry ``loss`` with: the one it
    trained at, except for an entry that trains at its recipe's own (a run saved before
    such entries refused --lr recorded the CLI default, which they did not use)."""
    if loss in registry.names() and registry.get(loss).own_lr is not None:
        return None
    return config.get("lr")


def migrated(state: dict[str, Any], learner: Learner) -> dict[str, Any]:
    """``state`` (a learner's saved weights) as ``learner`` holds them
    (:meth:`~imitrl.learners.Learner.migrated_state`: a checkpoint of imitrl up to
    d6e5639 keeps the ``value.*`` weights every ``ActorCritic`` had then)."""
    return learner.migrated_state({"learner": state})["learner"]


def _check_shapes(saved: SavedRun, state: dict, learner: Learner, env: EnvBase) -> None:
    """One line naming the first weight whose shape the learner rebuilt for ``env`` does not
    share (a learner evaluated in another env), rather than torch's list of every one."""
    want = learner.state_dict()
    bad = [  # weights only: a generator state is checked where it loads (SavedGenerator)
        k
        for k, v in state.items()
        if isinstance(v, torch.Tensor)
        and k in want
        and not k.endswith("_extra_state")
        and tuple(v.shape) != tuple(want[k].shape)
    ]
    if bad:
        trained = saved.config.get("env") or "a dataset"
        raise ValueError(
            f"{saved.path / WEIGHTS_FILE}: {bad[0]!r} is {list(state[bad[0]].shape)} but "
            f"{list(want[bad[0]].shape)} in a learner for this env ({len(bad)} weight(s) "
            f"differ): the checkpoint was trained on {trained}; evaluate it in an env with "
            "its observations and actions"
        )


def load_learner(checkpoint: Path, env: EnvBase, *, device: str | None = None) -> Learner:
    """The learner saved in ``checkpoint``, rebuilt for ``env`` on ``device`` (None: the
    CPU; the checkpoint may have been saved on another device) and loaded with its weights
    (:func:`read_checkpoint`, then :func:`build_learner`)."""
    return build_learner(read_checkpoint(checkpoint), env, device=device)


def build_learner(saved: SavedRun, env: EnvBase, *, device: str | None = None) -> Learner:
    """The learner of ``saved`` rebuilt for ``env`` on ``device`` and loaded with its
    weights; the network its config asks for is held to the weights' size with the env's
    observation and action sizes first (:func:`check_holds`)."""
    config = saved.config
    loss = saved_loss(saved.path, config["loss"])
    hidden = None if config.get("hidden") is None else tuple(config["hidden"])
    if hidden is not None and _builds_table(loss, env):
        hidden = None  # a table: runs before --hidden was optional recorded the default
    if hidden is not None:
        check_holds(saved.path / WEIGHTS_FILE, hidden, saved.weights_bytes, env)
    make = learner_factory(
        loss,
        env,
        hidden=hidden,
        lr=_saved_lr(config, loss),
        seed=config["seed"],
        device=device,
    )
    learner = make()
    state = migrated(saved.state, learner)
    _check_shapes(saved, state, learner, env)
    try:
        learner.load_state_dict(state)
    except ValueError as err:  # NaN weights, casts, copies that differ (check_saved_state)
        raise ValueError(f"{saved.path / WEIGHTS_FILE}: {err}") from None
    except RuntimeError as err:  # shapes or names that do not match the rebuilt learner
        raise ValueError(
            f"{saved.path}: the weights do not fit the rebuilt learner on {learner.device} ({err})"
        ) from err
    return learner

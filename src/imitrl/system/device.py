"""Where a learner computes, and how tensors cross to it (:func:`resolve_device`, :class:`OnDevice`).

One rule, end to end: envs and experts stay where they are (CPU gymnasium, any expert);
the learner (its policy, loss and optimizer) lives on one device, ``cpu`` or ``cuda:N``.

* ``device=`` accepts ``"auto"`` (CUDA when available, else the CPU), ``"cpu"``,
  ``"cuda"`` (the current CUDA device), ``"cuda:N"``, or a ``torch.device``;
  :func:`resolve_device` refuses anything else in one line naming what was asked and
  what this machine has.
* A fit's batches are read from rows on the CPU (a buffer in memory or on disk) and
  moved to the learner's device once per step, from pinned memory without blocking on
  CUDA (:func:`to_device`); the minibatch indices are drawn on the CPU from the fit's
  seeded generator, so a seed draws the same rows on every device.
* A rollout's policy call crosses once per batched step: the observations the policy
  reads go to the learner's device, the actions it writes come back to the env's
  (:class:`OnDevice`, which :func:`acting` puts around a module only when the two
  devices differ: on the CPU nothing changes, to the bit).
"""

from __future__ import annotations

import itertools
import re

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

__all__ = [
    "DEVICES", "OnDevice", "acting", "module_device", "on_cpu", "resolve_device", "to_device",
]  # fmt: skip

DEVICES = "auto, cpu, cuda or cuda:N"
"""what ``device=`` (``--device``) accepts"""


def _available() -> str:
    """What this machine has, for messages."""
    if not torch.cuda.is_available():
        built = torch.version.cuda
        how = (
            f"torch {torch.__version__} built with CUDA {built}"
            if built
            else (f"torch {torch.__version__} is a CPU build")
        )
        return f"no CUDA device ({how}); only cpu"
    n = torch.cuda.device_count()
    return "cpu and " + ", ".join(f"cuda:{i} ({torch.cuda.get_device_name(i)})" for i in range(n))


def resolve_device(device: str | torch.device | None) -> torch.device:
    """The ``torch.device`` that ``device`` names (see the module docstring).

    ``None`` and ``"auto"`` are CUDA when available, else the CPU.

    Raises:
        ValueError: an unknown name, CUDA on a machine without it, a CUDA index this
            machine does not have (the message lists what it has).
    """
    if device is None or (isinstance(device, str) and device.strip().lower() == "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if isinstance(device, torch.device):
        text = str(device)
    elif isinstance(device, str):
        text = device.strip().lower()
    else:
        raise ValueError(f"device must be {DEVICES}, got {device!r} ({type(device).__name__})")
    match = re.fullmatch(r"(cpu|cuda)(?::(\d+))?", text)
    if match is None or (match[1] == "cpu" and match[2] not in (None, "0")):
        raise ValueError(f"unknown device {device!r}: expected {DEVICES}")
    if match[1] == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise ValueError(f"device {device!r} asked for, but this machine has {_available()}")
    index = torch.cuda.current_device() if match[2] is None else int(match[2])
    if index >= torch.cuda.device_count():
        raise ValueError(f"device {device!r} asked for, but this machine has {_available()}")
    return torch.device("cuda", index)


def module_device(module: nn.Module) -> torch.device:
    """The device of ``module``'s first parameter (or buffer); the CPU when it has none."""
    for tensor in module.parameters():
        return tensor.device
    for buffer in module.buffers():
        return buffer.device
    return torch.device("cpu")


def on_cpu(data) -> bool:
    """Whether ``data`` (a tensor or a TensorDict) lives on the CPU. A TensorDict without
    a device of its own (``device=None``, what ``TensorDict(...)`` builds unless told)
    does when every leaf does."""
    if data.device is not None:
        return data.device.type == "cpu"
    devices = [getattr(v, "device", None) for v in data.values(True, True)]
    return bool(devices) and all(d is not None and d.type == "cpu" for d in devices)


def to_device(data, device: torch.device):
    """``data`` (a tensor or a TensorDict, with or without a device of its own) on
    ``device``: unchanged when it is there; from the CPU to CUDA through pinned memory,
    without blocking."""
    if device is None or data.device == device:
        return data
    if device.type == "cuda" and on_cpu(data):
        return data.pin_memory().to(device, non_blocking=True)
    return data.to(device)


class OnDevice(TensorDictModuleBase):
    """``module`` (on ``device``) acting on tensordicts of another device: the keys it
    reads go to ``device`` once per call, the keys it writes come back to the caller's.

    Args:
        module: a TensorDict module whose parameters live on ``device``.
        device: the module's device.
    """

    def __init__(self, module: TensorDictModuleBase, device: torch.device) -> None:
        super().__init__()
        self.module, self.device = module, torch.device(device)
        self.in_keys, self.out_keys = list(module.in_keys), list(module.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        inputs = tensordict.select(*self.in_keys, strict=False)
        out = self.module(to_device(inputs, self.device))
        present = [k for k in self.out_keys if k in out.keys(include_nested=True)]
        tensordict.update(out.select(*present).to(tensordict.device or "cpu"))
        return tensordict


def acting(
    module: TensorDictModuleBase, env_device: torch.device | str | None
) -> TensorDictModuleBase:
    """``module`` ready to act in an env on ``env_device``: itself when its parameters are
    there (the CPU case: the same calls, the same digits), else :class:`OnDevice`.

    Parameters inside an :class:`OnDevice` within ``module`` cross on their own and are
    not counted: DAgger's behaviour policy (a CPU expert, and the learner already wrapped)
    acts as it is, and its expert reads the env's tensors where they are."""
    env_device = torch.device(env_device or "cpu")
    if isinstance(module, OnDevice):
        return module
    crossing = {
        id(t)
        for m in module.modules()
        if isinstance(m, OnDevice)
        for t in itertools.chain(m.parameters(), m.buffers())
    }
    own = itertools.chain(module.parameters(), module.buffers())
    # no parameter of its own: a CPU function (an expert), as module_device says
    here = next((t.device for t in own if id(t) not in crossing), torch.device("cpu"))
    if here == env_device:
        return module
    return OnDevice(module, here)

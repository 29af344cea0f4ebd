"""imitrl: imitation learning on TorchRL, checked against exact tabular ground truth.

``import imitrl`` imports nothing else: each subpackage (``imitrl.algorithms``,
``imitrl.tabular``, ...) is imported on its first access (PEP 562), so the command line
and ``--help`` start without torch; the subpackages that need torch, TorchRL and
tensordict import them themselves.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping

__version__ = "0.1.0"


def __getattr__(name: str):
    """``imitrl.<submodule>``, imported on first access (then a plain attribute)."""
    import importlib.util  # here, as pkgutil below: ``import imitrl`` imports neither

    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    """The module's names and every submodule's."""
    import pkgutil

    return sorted({*globals(), *(m.name for m in pkgutil.iter_modules(__path__))})


def _lazy_exports(
    package: str, exports: Mapping[str, str]
) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """PEP 562 ``__getattr__`` and ``__dir__`` for ``package``: ``exports`` maps each public
    name to the module that defines it, imported on the name's first access (the value
    is then kept as a plain attribute of ``package``). ``from package import name`` and
    ``package.name`` work as with an eager import; only the cost moves to first use."""
    module = sys.modules[package]

    def __getattr__(name: str) -> object:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(exports[name]), name)
        setattr(module, name, value)
        return value

    def __dir__() -> list[str]:
        return sorted({*vars(module), *exports})

    return __getattr__, __dir__

"""Importing code the user named (``--env module:Env-v0``, ``--expert module:function``,
``--loss module:name``): the one place that turns whatever the import raised into a
one-line error naming the module and the flag, instead of a traceback through imitrl.

Only modules the user named on the command line (or passed in Python) are imported: a
dataset, checkpoint or config never names code that imitrl then runs.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["import_user_module"]


def import_user_module(module: str, what: str) -> ModuleType:
    """``importlib.import_module(module)``, for ``what`` (the flag and value, as the
    message should name them).

    Raises:
        ValueError: the module is missing, or its own code raised while importing (a
            ``SyntaxError``, a ``RuntimeError`` of its own, ``sys.exit()``): the message
            names the error and keeps it as ``__cause__`` for a debugger.
    """
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ValueError(f"{what}: cannot import {module!r} ({err})") from err
    except SystemExit as err:  # a script's sys.exit() or argparse at import: not a run's end
        raise ValueError(
            f"{what}: cannot import {module!r}: importing it called sys.exit({err.code!r})"
        ) from err
    except Exception as err:
        raise ValueError(
            f"{what}: cannot import {module!r}: importing it raised {type(err).__name__}: {err}"
        ) from err

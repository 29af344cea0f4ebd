"""``imitrl.cli.main`` run in this process, with what it printed."""

from __future__ import annotations

import contextlib
import io

from imitrl.cli import main


def run_main(*argv: str) -> tuple[int, str, str]:
    """``main(argv)``: (status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(list(argv))
    return status, out.getvalue(), err.getvalue()

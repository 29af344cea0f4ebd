"""Code the user named is imported in one place (:mod:`imitrl.system.imports`): whatever
its import raises is a one-line error naming the flag and the module (a hostile review: a
``--loss`` module raising a ``RuntimeError`` at import printed a traceback through imitrl)."""

from __future__ import annotations

import pytest

from imitrl.system.imports import import_user_module
from tests._cli import run_main


@pytest.fixture
def broken(tmp_path, monkeypatch):
    """Modules on ``sys.path`` that fail to import, each in its own way."""
    (tmp_path / "raises_at_import.py").write_text("raise RuntimeError('no licence file')\n")
    (tmp_path / "bad_syntax.py").write_text("def f(:\n")
    (tmp_path / "needs_missing.py").write_text("import no_such_dependency_q\n")
    (tmp_path / "exits_at_import.py").write_text("import sys\nsys.exit(0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


@pytest.mark.parametrize(
    "module, said",
    [
        ("raises_at_import", "importing it raised RuntimeError: no licence file"),
        ("bad_syntax", "importing it raised SyntaxError"),
        ("needs_missing", "No module named 'no_such_dependency_q'"),
        ("no_such_module_q", "No module named 'no_such_module_q'"),
        # a hostile review: the run exited 0, printing and writing nothing
        ("exits_at_import", "importing it called sys.exit(0)"),
    ],
)
def test_every_import_failure_is_a_value_error_naming_the_flag(broken, module, said):
    with pytest.raises(ValueError, match=f"--loss 'x': cannot import '{module}'") as err:
        import_user_module(module, "--loss 'x'")
    assert said in str(err.value)
    assert err.value.__cause__ is not None  # the original error stays for a debugger


def test_a_module_that_imports_is_returned(broken):
    (broken / "fine_module_q.py").write_text("VALUE = 7\n")
    assert import_user_module("fine_module_q", "--expert 'fine_module_q:VALUE'").VALUE == 7


@pytest.mark.parametrize(
    "flags",
    [
        ["--loss", "raises_at_import:mine"],
        ["--expert", "raises_at_import:act"],
        ["--env", "raises_at_import:Mine-v0"],
    ],
)
def test_the_cli_says_it_in_one_line_for_each_flag(broken, flags):
    argv = ["bc", "--env", "Pendulum-v1", *flags, "--no-progress"]
    if flags[0] == "--env":
        argv = ["bc", *flags, "--no-progress"]
    status, _, err = run_main(*argv)
    assert status == 2, err
    assert "importing it raised RuntimeError: no licence file" in err
    assert "Traceback" not in err

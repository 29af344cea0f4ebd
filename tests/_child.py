"""Child processes for tests, forked from one process that imported torch, tensordict,
TorchRL and gymnasium once, instead of a fresh interpreter that pays ~3 s of CPU for those
imports each time (about a third of the default suite's CPU went to them).

    done = _child.run([sys.executable, "-m", "imitrl", "bc", ...], capture_output=True,
                      text=True, env=env, cwd=cwd, timeout=300)
    proc = _child.Popen([sys.executable, "-c", CODE, *args], stdout=subprocess.DEVNULL)
    ctx = _child.context()  # for multiprocessing.Process(target=...) children

take the arguments of :func:`subprocess.run` and :class:`subprocess.Popen` that the tests
use, and give what they give (``returncode``, ``stdout``, ``stderr``, ``pid``, ``poll``,
``wait``, ``kill``, ``send_signal``, ``communicate``). The child is a fork of
multiprocessing's fork server, whose preload (:data:`PRELOAD`) is the third-party libraries
alone: ``imitrl`` and the test's own code are imported in the child, from its
``PYTHONPATH``, as a fresh interpreter would import them. The child runs ``-m MODULE``,
``-c CODE`` or ``SCRIPT`` as ``python`` would (``sys.argv``, ``sys.path[0]``, ``__main__``,
the exit status of ``SystemExit``, a traceback and status 1 for an uncaught exception, a
death by SIGINT for an uncaught ``KeyboardInterrupt``, non-daemon threads joined and exit
handlers run at its end), in ``cwd``, with ``env`` as its whole environment.

What stays a fresh interpreter (a plain :mod:`subprocess` call; these functions fall back to
one themselves): a command that is not ``python -m/-c/SCRIPT`` (``-X importtime``, ``-u``,
another program), and an ``env`` that changes a variable the preloaded libraries read as they
are imported (:data:`READ_AT_IMPORT`). A test about what a fresh interpreter imports, how
it starts, or how much memory its imports take calls :mod:`subprocess` itself.
"""

from __future__ import annotations

import atexit
import importlib
import json
import multiprocessing
import multiprocessing.forkserver
import os
import runpy
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import types
from pathlib import Path

PRELOAD = [
    "numpy",
    "torch",
    "tensordict",
    "tensordict.nn",
    "torchrl",
    "torchrl.envs",
    "torchrl.data",
    "torchrl.modules",
    "torchrl.objectives",
    "torchrl.collectors",
    "torchrl.record.loggers",
    "gymnasium",
]
"""what the fork server imports once: third-party libraries that read nothing of the
test's own (imitrl is imported by each child)"""
READ_AT_IMPORT = ("PYTHON", "OMP_", "MKL_", "KMP_", "TORCH", "PYTORCH", "CUDA", "MUJOCO",
                  "PYOPENGL", "PYGLFW", "RAY_")  # fmt: skip
"""prefixes of environment variables that a preloaded library reads as it is imported: a
child whose ``env`` gives one of them another value than the fork server's gets a fresh
interpreter (``PYTHONPATH`` excepted: the child puts it on ``sys.path`` itself)"""

for _name in PRELOAD:  # what they set as they are imported (RAY_CLIENT_MODE) is set here too
    importlib.import_module(_name)
_SESSION_ENV = dict(os.environ)
"""the environment when the tests were collected (this module is imported then), with what
the preloaded libraries set as they are imported, before a test sets anything of its own"""
_server: multiprocessing.context.BaseContext | None = None
_fresh_path: list[str] | None = None


def _context() -> multiprocessing.context.BaseContext:
    """multiprocessing's fork server with its preload set, started at the first child with
    the environment the session started with (:data:`_SESSION_ENV`, not a test's own)."""
    global _server
    if _server is None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(PRELOAD)
        now = dict(os.environ)
        os.environ.clear()
        os.environ.update(_SESSION_ENV)
        try:
            multiprocessing.forkserver.ensure_running()  # it inherits this environment
        finally:
            os.environ.clear()
            os.environ.update(now)
        _server = ctx
    return _server


def context() -> multiprocessing.context.BaseContext:
    """multiprocessing's fork server context with :data:`PRELOAD` imported once: for a test's
    own ``Process`` (or ``torch.multiprocessing.start_processes(...,
    start_method="forkserver")``, which uses the same server), where ``spawn`` would pay the
    imports in every process."""
    return _context()


def forkserver() -> str:
    """``"forkserver"``, with :data:`PRELOAD` set for its server: the ``start_method`` of
    ``torch.multiprocessing.start_processes`` (what ``spawn`` would give, without paying the
    imports in every rank)."""
    _context()
    return "forkserver"


def _default_path() -> list[str]:
    """``sys.path`` of a fresh interpreter without ``PYTHONPATH``, after its first entry."""
    global _fresh_path
    if _fresh_path is None:
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        done = subprocess.run(
            [sys.executable, "-S", "-c", "import sys, json, site; site.main(); "
             "print(json.dumps(sys.path[1:]))"],
            capture_output=True, text=True, env=env, check=True, cwd="/",
        )  # fmt: skip
        _fresh_path = json.loads(done.stdout)
    return _fresh_path


def _forkable(args: list[str], env: dict[str, str]) -> bool:
    if not args or args[0] != sys.executable or len(args) < 2:
        return False
    if args[1].startswith("-") and args[1] not in ("-m", "-c"):
        return False
    if args[1] in ("-m", "-c") and len(args) < 3:
        return False
    return all(
        env.get(k) == _SESSION_ENV.get(k)
        for k in {*env, *_SESSION_ENV}
        if k.startswith(READ_AT_IMPORT) and k != "PYTHONPATH"
    )


def _open_out(where) -> tuple[int | None, Path | None]:
    """What the child's fd 1 or 2 becomes: None (inherited), DEVNULL, or a file to read."""
    if where is None:
        return None, None
    if where == subprocess.DEVNULL:
        return os.open(os.devnull, os.O_WRONLY), None
    if where == subprocess.PIPE:
        fd, name = tempfile.mkstemp(prefix="imitrl-child-")
        return fd, Path(name)
    if where == subprocess.STDOUT:
        return -2, None
    raise ValueError(f"stdout/stderr {where!r}: None, DEVNULL, PIPE or STDOUT")


class Popen:
    """A forked child, as :class:`subprocess.Popen` of ``args`` would start it (module
    docstring); a fresh interpreter where it cannot be a fork."""

    def __init__(self, args, *, stdout=None, stderr=None, text=False, env=None, cwd=None):
        args = [str(a) for a in args]
        env = dict(os.environ if env is None else env)
        self.args, self.text = args, text
        self.returncode: int | None = None
        self._plain: subprocess.Popen | None = None
        if not _forkable(args, env):
            self._plain = subprocess.Popen(
                args, stdout=stdout, stderr=stderr, text=text, env=env, cwd=cwd
            )
            self.pid = self._plain.pid
            return
        out_fd, self._out = _open_out(stdout)
        err_fd, self._err = _open_out(stderr)
        ctx = _context()
        pythonpath = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
        fds = [fd for fd in (out_fd, err_fd) if fd is not None and fd >= 0]
        wrap = lambda fd: _Fd(fd) if fd is not None and fd >= 0 else fd  # noqa: E731
        self._proc = ctx.Process(
            target=_main,
            args=(args[1:], env, os.path.abspath(cwd or os.getcwd()),
                  [*pythonpath, *_default_path()], wrap(out_fd), wrap(err_fd)),
        )  # fmt: skip
        try:
            self._proc.start()
        finally:
            for fd in fds:
                os.close(fd)
        # as subprocess leaves its children: this process's exit does not wait for it
        # (multiprocessing's exit handler joins the Process objects it still lists)
        multiprocessing.process._children.discard(self._proc)  # type: ignore[attr-defined]
        self.pid = self._proc.pid

    def poll(self) -> int | None:
        if self._plain is not None:
            self.returncode = self._plain.poll()
        elif self.returncode is None and self._proc.exitcode is not None:
            self.returncode = self._proc.exitcode
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self._plain is not None:
            self.returncode = self._plain.wait(timeout)
            return self.returncode
        self._proc.join(timeout)
        if self.poll() is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def _read(self, path: Path | None):
        if path is None:
            return None
        data = path.read_bytes()
        path.unlink(missing_ok=True)
        return data.decode(errors="replace") if self.text else data

    def communicate(self, timeout: float | None = None):
        if self._plain is not None:
            out = self._plain.communicate(timeout=timeout)
            self.returncode = self._plain.returncode
            return out
        self.wait(timeout)
        return self._read(self._out), self._read(self._err)

    def __enter__(self) -> Popen:
        return self

    def __exit__(self, *exc) -> None:
        if self.poll() is None:
            self.kill()
        self.wait()
        for path in (getattr(self, "_out", None), getattr(self, "_err", None)):
            if path is not None:
                path.unlink(missing_ok=True)


def run(args, *, capture_output=False, text=False, env=None, cwd=None, timeout=None,
        check=False, stdout=None, stderr=None) -> subprocess.CompletedProcess:  # fmt: skip
    """:func:`subprocess.run` of ``args`` as a forked child (module docstring)."""
    if capture_output:
        stdout = stderr = subprocess.PIPE
    proc = Popen(args, stdout=stdout, stderr=stderr, text=text, env=env, cwd=cwd)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise
    done = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    if check:
        done.check_returncode()
    return done


class _Fd:
    """An fd of this process that the child gets a copy of: pickled for the fork server
    as multiprocessing pickles a connection (:func:`multiprocessing.reduction.DupFd`)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def __reduce__(self):
        from multiprocessing import reduction

        return _Fd._inherited, (reduction.DupFd(self.fd),)

    @staticmethod
    def _inherited(dup) -> int:
        return dup.detach()


# ------------------------------------------------------------------ in the child
def _main(argv, env, cwd, path, out_fd, err_fd) -> None:
    """The child: ``python ARGV`` in ``cwd`` with ``env``; never returns."""
    status = 1
    try:
        for fd, target in ((out_fd, 1), (err_fd, 2)):
            if fd is not None:
                os.dup2(1 if fd == -2 else fd, target)
        os.chdir(cwd)
        os.environ.clear()
        os.environ.update(env)
        tempfile.tempdir = None  # gettempdir() reads TMPDIR again
        if "OMP_NUM_THREADS" in env:
            import torch

            torch.set_num_threads(int(env["OMP_NUM_THREADS"]))
        status = run_program(argv, path)
    except BaseException:
        traceback.print_exc()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass
        os._exit(status)


def run_program(argv: list[str], path: list[str]) -> int:
    """Run ``python ARGV``'s program (``-m MODULE``, ``-c CODE`` or ``SCRIPT``, then its
    arguments) in this process as ``__main__``, with ``path`` after ``sys.path[0]``, as
    the interpreter would run it to its exit (module docstring): its exit status. The
    benchmarks' smoke run (``tests/benchmarks/_preloaded.py``) runs its scripts with it."""
    kind = argv[0]
    if kind == "-m":
        sys.argv = ["-m", *argv[2:]]  # runpy puts the module's file first
        sys.path[:] = [os.getcwd(), *path]
        body = lambda: runpy.run_module(argv[1], run_name="__main__", alter_sys=True)  # noqa: E731
    elif kind == "-c":
        sys.argv = ["-c", *argv[2:]]
        sys.path[:] = ["", *path]
        main = types.ModuleType("__main__")
        sys.modules["__main__"] = main
        compiled = compile(argv[1], "<string>", "exec")
        body = lambda: exec(compiled, main.__dict__)  # noqa: E731
    else:
        script = os.path.abspath(kind)
        sys.argv = list(argv)
        sys.path[:] = [os.path.dirname(script), *path]
        body = lambda: runpy.run_path(script, run_name="__main__")  # noqa: E731
    status = 0
    try:
        body()
    except SystemExit as done:
        code = done.code
        status = code if isinstance(code, int) else (0 if code is None else 1)
        if not isinstance(code, int | None):
            print(code, file=sys.stderr)
    except KeyboardInterrupt:
        traceback.print_exc()
        sys.stderr.flush()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)  # as python dies of an uncaught one
        time.sleep(1)
    except BaseException:
        traceback.print_exc()
        status = 1
    try:
        threading._shutdown()  # type: ignore[attr-defined]  # python joins them at exit
        atexit._run_exitfuncs()
    except BaseException:
        traceback.print_exc()
        status = status or 1
    return status

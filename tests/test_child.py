"""``tests/_child.py``: a forked child runs ``python -m/-c/SCRIPT`` as a fresh interpreter
would (what it sees, prints and exits with), and falls back to one where it cannot."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import textwrap

import pytest

from tests import _child

PROBE = textwrap.dedent(
    """
    import atexit, json, os, sys, tempfile, threading, time
    atexit.register(lambda: print("at exit", flush=True))
    def late():
        time.sleep(0.2)
        print("thread joined", flush=True)
    threading.Thread(target=late).start()  # python joins it before the exit handlers
    print(json.dumps({
        "argv": sys.argv[1:], "path": sys.path, "name": __name__, "cwd": os.getcwd(),
        "tmp": tempfile.gettempdir(), "probe": os.environ.get("PROBE"),
        "imitrl_path": os.environ.get("PYTHONPATH", "").split(os.pathsep)[0] in sys.path,
    }))
    print("to stderr", file=sys.stderr)
    raise SystemExit(int(sys.argv[1]) if sys.argv[1:] else "a message")
    """
)


def _both(args, tmp_path, **kwargs):
    """``args`` run fresh and as a fork: their (returncode, stdout, stderr)."""
    env = {**os.environ, "PROBE": "x", "TMPDIR": str(tmp_path), "PYTHONPATH": str(tmp_path)}
    runs = []
    for run in (subprocess.run, _child.run):
        done = run(args, capture_output=True, text=True, env=env, timeout=120, **kwargs)
        runs.append((done.returncode, done.stdout, done.stderr))
    return runs


@pytest.mark.parametrize("kind", ["-c", "-m", "script"])
def test_a_fork_runs_the_program_as_a_fresh_interpreter(tmp_path, kind):
    (tmp_path / "probe_mod.py").write_text(PROBE)
    program = {
        "-c": ["-c", PROBE],
        "-m": ["-m", "probe_mod"],
        "script": [str(tmp_path / "probe_mod.py")],
    }[kind]
    fresh, fork = _both([sys.executable, *program, "3", "more"], tmp_path, cwd=tmp_path)
    assert fresh == fork
    status, out, err = fork
    assert status == 3 and err == "to stderr\n"
    said = json.loads(out.splitlines()[0])
    assert said["argv"] == ["3", "more"] and said["probe"] == "x" and said["imitrl_path"]
    assert out.splitlines()[1:] == ["thread joined", "at exit"]
    # SystemExit with a message: printed on stderr, status 1
    assert _both([sys.executable, *program], tmp_path, cwd=tmp_path)[1][0] == 1


def test_a_fork_dies_as_python_dies(tmp_path):
    for code, status, said in [
        ("raise ValueError('boom')", 1, "ValueError: boom"),
        ("raise KeyboardInterrupt", -signal.SIGINT, "KeyboardInterrupt"),
        ("import os, signal; os.kill(os.getpid(), signal.SIGTERM)", -signal.SIGTERM, ""),
    ]:
        fresh, fork = _both([sys.executable, "-c", code], tmp_path)
        assert fresh[0] == fork[0] == status, (code, fresh, fork)
        assert said in fork[2] and said in fresh[2]


def test_a_popen_is_killed_waited_and_timed_out():
    proc = _child.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    assert proc.poll() is None
    # left as subprocess leaves a child: this process's exit would not wait for it
    assert proc.pid not in [c.pid for c in multiprocessing.active_children()]
    proc.send_signal(signal.SIGKILL)
    assert proc.wait(timeout=30) == -signal.SIGKILL
    with pytest.raises(subprocess.TimeoutExpired):
        _child.run([sys.executable, "-c", "import time; time.sleep(60)"], timeout=1)
    merged = _child.run(
        [sys.executable, "-c", "import sys; print('out'); print('err', file=sys.stderr)"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert merged.stdout == "out\nerr\n" and merged.stderr is None


def test_only_what_can_be_a_fork_is_one():
    """A fork's parent is the fork server and it starts with torch imported; a command
    that is not ``python -m/-c/SCRIPT``, or an env that changes what torch read as it was
    imported, gets a fresh interpreter: this process's child, torch not imported."""
    probe = "import os, sys; print(os.getppid(), 'torch' in sys.modules)"
    session = dict(_child._SESSION_ENV)  # not what another file's fixtures left set
    threads = {**session, "OMP_NUM_THREADS": "2"}
    for args, env, fork in [
        ([sys.executable, "-c", probe], session, True),
        ([sys.executable, "-X", "utf8", "-c", probe], session, False),
        ([sys.executable, "-c", probe], threads, False),
    ]:
        done = _child.run(args, capture_output=True, text=True, env=env, check=True)
        parent, torch_loaded = done.stdout.split()
        assert (int(parent) != os.getpid()) == fork and torch_loaded == str(fork), (
            args, _changed(env)
        )  # fmt: skip


def test_the_server_starts_with_the_sessions_environment(monkeypatch):
    """A test that sets a variable the preloaded libraries read (here before the server's
    first child, if it is the first) sends its own children to fresh interpreters, and
    never the later tests' children: the server keeps the session's environment."""
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    probe = "import os, sys; print(os.getppid())"
    done = _child.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert int(done.stdout) == os.getpid()  # fresh: this test's own setting
    session = dict(_child._SESSION_ENV)  # a later test's (not what a fixture left set)
    done = _child.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True,
                      env=session)  # fmt: skip
    assert int(done.stdout) != os.getpid(), _changed(session)  # a fork: the session's setting


def _changed(env: dict[str, str] | None) -> list[tuple[str, str | None, str | None]]:
    """What ``env`` (this process's by default) sets otherwise than the session did, of
    what the preloaded libraries read as they are imported: why a child went fresh."""
    env = dict(os.environ if env is None else env)
    return sorted(
        (k, env.get(k), _child._SESSION_ENV.get(k))
        for k in {*env, *_child._SESSION_ENV}
        if k.startswith(_child.READ_AT_IMPORT) and env.get(k) != _child._SESSION_ENV.get(k)
    )

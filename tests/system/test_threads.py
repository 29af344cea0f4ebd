"""torch's threads: ``--threads N`` on every command, the default, each worker's share.

The commands run in-process (``imitrl.cli.main``); the command's function is wrapped to
read ``torch.get_num_threads()`` while it runs. Every test leaves torch at one thread,
as ``conftest.py`` set it.
"""

from __future__ import annotations

import contextlib
import io
import os

import pytest
import torch

from imitrl.cli import COMMANDS, build_parser, main
from imitrl.jobs import bench, evaluate
from imitrl.system import threads

EVAL = [
    "eval", "--expert", "cartpole", "--env", "CartPole-v1", "--eval-episodes", "1",
    "--max-episode-steps", "5", "--no-progress",
]  # fmt: skip


@pytest.fixture(autouse=True)
def one_thread_after():
    yield
    torch.set_num_threads(1)


def run(argv: list[str]) -> tuple[int, str, str]:
    """``main(argv)`` with stdout and stderr captured: (status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


@pytest.fixture
def threads_seen(monkeypatch) -> list[int]:
    """torch's threads inside every ``imitrl eval`` run of the test (the real job runs)."""
    seen: list[int] = []
    real = evaluate.run_eval

    def spy(config):
        seen.append(torch.get_num_threads())
        return real(config)

    monkeypatch.setattr(evaluate, "run_eval", spy)
    return seen


def test_the_flag_sets_torchs_threads_for_the_command(threads_seen):
    status, stdout, stderr = run([*EVAL, "--threads", "2"])
    assert status == 0, stderr
    assert threads_seen == [2]
    assert "return" in stdout.lower()  # the evaluation itself ran and reported


def test_the_default_is_one_thread_whatever_torch_had(threads_seen):
    assert threads.DEFAULT_THREADS == 1
    torch.set_num_threads(2)  # torch's own default on a 2-core machine
    status, _, stderr = run(EVAL)
    assert status == 0, stderr
    assert threads_seen == [1]


@pytest.mark.parametrize("value", ["0", "-3"])
def test_bad_values_exit_2_with_one_line(value, threads_seen):
    status, stdout, stderr = run([*EVAL, "--threads", value])
    assert status == 2
    assert stderr == f"imitrl eval: --threads must be an integer >= 1, got {value}\n"
    assert stdout == "" and threads_seen == []  # refused before the command ran


def test_a_non_number_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([*EVAL, "--threads", "two"])
    assert exit_info.value.code == 2
    assert "argument --threads: invalid int value: 'two'" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_takes_the_flag_with_the_default(name):
    positional = {"bench": ["some_benchmark"], "compare": ["--a", "expert", "--b", "random"]}
    positional = positional.get(name, [])  # what the command requires
    args = build_parser([name]).parse_args([name, *positional])
    assert args.threads == threads.DEFAULT_THREADS
    args = build_parser([name]).parse_args([name, "--threads", "3", *positional])
    assert args.threads == 3


def test_bench_gives_the_script_its_threads(tmp_path, monkeypatch, capfd):
    script = "import os, torch\nprint(os.environ['OMP_NUM_THREADS'], torch.get_num_threads())\n"
    (tmp_path / "show_threads.py").write_text(script)
    monkeypatch.setattr(bench, "BENCHMARKS_DIR", tmp_path)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert main(["bench", "--threads", "2", "show_threads"]) == 0
    assert capfd.readouterr().out.split() == ["2", "2"]
    assert "OMP_NUM_THREADS" not in os.environ  # this process's environment is as it was
    assert main(["bench", "show_threads"]) == 0
    assert capfd.readouterr().out.split() == ["1", "1"]
    assert run(["bench", "--threads", "0", "show_threads"])[2] == (
        "imitrl bench: --threads must be an integer >= 1, got 0\n"
    )


def test_set_threads_sets_and_refuses():
    assert threads.set_threads(2) == 2 and torch.get_num_threads() == 2
    assert threads.set_threads(None) == 1 and torch.get_num_threads() == 1
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="threads must be an integer >= 1"):
            threads.set_threads(bad)
    assert torch.get_num_threads() == 1


@pytest.mark.parametrize(
    ("cores", "workers", "want", "each"),
    [
        (2, 1, None, 1),  # the default: one thread, even alone
        (2, 2, None, 1),
        (2, 1, 2, 2),  # asked for two, and the machine has them
        (2, 1, 4, 2),  # never more than the cores
        (2, 2, 2, 1),  # two workers share two cores
        (2, 3, 2, 1),  # more workers than cores: still one each, never zero
        (16, 4, 8, 4),
    ],
)
def test_worker_threads_never_oversubscribe(monkeypatch, cores, workers, want, each):
    monkeypatch.setattr(threads, "cores", lambda: cores)
    assert threads.worker_threads(workers, want) == each
    assert workers * each <= max(cores, workers)


def test_worker_threads_refuses_bad_counts():
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got 0"):
        threads.worker_threads(0)
    with pytest.raises(ValueError, match="threads must be an integer >= 1, got 0"):
        threads.worker_threads(1, 0)


def test_the_system_package_exports_both_modules():
    from imitrl import system
    from imitrl.system import device

    assert system.set_threads is threads.set_threads
    assert system.worker_threads is threads.worker_threads
    assert system.resolve_device is device.resolve_device
    assert system.OnDevice is device.OnDevice
    assert {"acting", "module_device", "to_device"} <= set(dir(system))

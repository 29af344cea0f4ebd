"""``--address``: a cluster nobody listens at is refused at once, before any work (a
review: ``127.0.0.1:1`` had not failed after 120 s, ``ray://nohost:1`` failed after the
demonstrations and the first fit with Ray's 58-line traceback)."""

from __future__ import annotations

import socket

import pytest

from imitrl.algorithms.ray_setup import check_address
from tests._cli import run_main


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("form", ["127.0.0.1:{port}", "ray://127.0.0.1:{port}"])
def test_an_address_nobody_listens_at_is_refused(form):
    address = form.format(port=_closed_port())
    with pytest.raises(ValueError, match=r"nothing accepts a connection at 127\.0\.0\.1:\d+"):
        check_address(address)


def test_an_address_that_accepts_passes_and_other_forms_are_rays():
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        check_address(f"127.0.0.1:{server.getsockname()[1]}")
    check_address("auto")  # Ray resolves it (RAY_ADDRESS, a running head node)


def test_dagger_with_a_dead_address_stops_before_the_demonstrations(tmp_path):
    status, _, err = run_main("dagger", "--env", "CartPole-v1", "--demos", "1", "--rounds", "2",
                              "--steps", "5", "--workers", "2", "--address",
                              f"127.0.0.1:{_closed_port()}", "--eval-episodes", "1",
                              "--no-progress", "--out", str(tmp_path / "o"))  # fmt: skip
    assert status == 2 and "nothing accepts a connection" in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "o").exists()

"""Every code block of the README is run by a test as written, or marked as a fragment.

A named block (``<!-- BEGIN name -->`` ... ``<!-- END name -->``) is run twice in one
folder by :func:`tests._readme.run`: first in a fresh interpreter, whose standard output
must be exactly the documented ``# ...`` lines after each ``print`` (nothing before them:
no logger line, no encoder chatter), then in the test's process. A block that cannot
run as a test (a fresh install, a cluster) says so on the line before it:
``<!-- fragment: why -->``. Text blocks without a language (the layout) are not code.
"""

from __future__ import annotations

import re

import pytest

from ._readme import README, run

FENCE = re.compile(r"^```(\w+)\n.*?^```", re.M | re.S)
CODE = ("python", "bash", "sh", "shell", "console")


def _blocks() -> list[tuple[int, str, str | None, bool]]:
    """``(line, language, name, fragment)`` of every code block of the README."""
    text = README.read_text()
    named = [
        (m.start(), m.end(), m.group(1))
        for m in re.finditer(r"<!-- BEGIN (\S+) -->.*?<!-- END \1 -->", text, flags=re.S)
    ]
    out = []
    for m in FENCE.finditer(text):
        if m.group(1) not in CODE:
            continue
        name = next((n for a, b, n in named if a < m.start() < b), None)
        before = text[: m.start()].rstrip().splitlines()
        fragment = bool(before) and before[-1].startswith("<!-- fragment:")
        out.append((text.count("\n", 0, m.start()) + 1, m.group(1), name, fragment))
    return out


def test_every_code_block_is_run_by_a_test_or_marked_a_fragment():
    blocks = _blocks()
    assert len(blocks) >= 8
    unmarked = [(line, lang) for line, lang, name, fragment in blocks if not name and not fragment]
    assert unmarked == [], f"README code blocks neither named nor marked as fragments: {unmarked}"
    named = {name for _, lang, name, _ in blocks if name and lang == "python"}
    tested = {"pieces-example", "lerobot-example", "continuous-example", "camera-example",
              "disk-buffer-example", "metaworld-example"}  # fmt: skip
    assert named == tested, f"named blocks without a test here or elsewhere: {named - tested}"


def test_disk_buffer_example_runs_twice_and_continues_its_buffer(tmp_path):
    ns, printed = run("disk-buffer-example", tmp_path)
    assert printed == ["0"]
    buffer = ns["buffer"]
    assert buffer.num_episodes == 4  # the fresh interpreter's 2 episodes, then this run's 2
    assert sorted(buffer.data["episode"].unique().tolist()) == list(range(4))


@pytest.mark.parametrize("name", ["pieces-example"])
def test_a_block_that_prints_an_extra_line_fails(tmp_path, monkeypatch, name):
    """The check can fail: a block printing one line more than it documents is refused."""
    from . import _readme

    original = _readme.block
    monkeypatch.setattr(_readme, "block", lambda n: "print('hello')\n" + original(n))
    with pytest.raises(AssertionError, match="printed"):
        _readme.run_fresh(name, tmp_path)

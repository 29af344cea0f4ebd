"""Every code block of the README and of the site's pages is run, or marked as a fragment.

A named block (``<!-- BEGIN name -->`` ... ``<!-- END name -->``, in ``README.md`` or a
page under ``docs/``) is run twice in one folder by :func:`tests._readme.run`: first in
a fresh interpreter, whose standard output must be exactly the documented ``# ...``
lines after each ``print`` (nothing before them: no logger line, no encoder chatter),
then in the test's process. A block markdown-exec runs (``exec="on"`` on its fence) runs
when the site is built (``mkdocs build --strict`` in ``.ci/run``), which fails on an
error or a non-zero exit. A block that can run neither way (a fresh install, a cluster,
a benchmark) says so on the line before it: ``<!-- fragment: why -->``. Text blocks
without a language (the layout) are not code.
"""

from __future__ import annotations

import re

import pytest

from ._readme import DOCS, README, ROOT, pages, run

FENCE = re.compile(r"^```(\w+)([^\n]*)\n.*?^```", re.M | re.S)
CODE = ("python", "bash", "sh", "shell", "console")


def _blocks(page) -> list[tuple[int, str, str | None, bool, bool]]:
    """``(line, language, name, fragment, run at build)`` of every code block of a page."""
    text = page.read_text()
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
        executed = 'exec="on"' in m.group(2)
        line = text.count("\n", 0, m.start()) + 1
        out.append((line, m.group(1), name, fragment, executed))
    return out


def test_every_code_block_is_run_by_a_test_or_the_build_or_marked_a_fragment():
    blocks = {p.relative_to(ROOT).as_posix(): _blocks(p) for p in pages()}
    assert sum(len(b) for b in blocks.values()) >= 20
    unmarked = [
        (page, line, lang)
        for page, found in blocks.items()
        for line, lang, name, fragment, executed in found
        if not name and not fragment and not executed
    ]
    assert unmarked == [], f"code blocks neither named, run at build nor fragments: {unmarked}"
    named = [
        name
        for found in blocks.values()
        for _, lang, name, _, _ in found
        if name and lang == "python"
    ]
    tested = {"pieces-example", "lerobot-example", "continuous-example", "camera-example",
              "disk-buffer-example", "metaworld-example"}  # fmt: skip
    assert sorted(named) == sorted(tested), f"named blocks, each once, each with a test: {named}"


def test_the_tutorials_run_their_cheap_blocks_at_build():
    """Every named block but the camera tutorial's (about 40 s; its test runs it) runs when
    the site is built, so the page's output is that code's output."""
    slow = {"camera-example"}
    for page in sorted((DOCS / "tutorials").glob("*.md")):
        for _, lang, name, _, executed in _blocks(page):
            if name and lang == "python":
                assert executed == (name not in slow), f"{page.name}: {name}"


def test_the_readme_is_a_front_door_to_the_site():
    """Under 12 KB, the two set-up commands as they were, and every link it makes to a
    file of the repository (the site's pages) leads to one."""
    text = README.read_text()
    assert len(text.encode()) < 12 * 1024, len(text.encode())
    for command in (
        "python3 -m venv .venv && .venv/bin/pip install torch==2.13.0 && .venv/bin/pip "
        "install -e . && .venv/bin/imitrl frozenlake --out results/frozenlake",
        "python3 -m venv .venv && .venv/bin/pip install torch==2.13.0 && .venv/bin/pip "
        'install -e ".[dev,datasets,mujoco,distributed,hub,metaworld]" && .venv/bin/python '
        "-m pytest -q && .venv/bin/mypy",
    ):
        assert command in text
    assert ".venv/bin/mkdocs build --strict" in text
    links = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text)
    local = [link for link in links if "://" not in link]
    assert local and all((ROOT / link).exists() for link in local), local
    assert any(link.startswith("docs/") for link in local)


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

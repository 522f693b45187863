"""The outputs the README shows are what the commands print today (tests/readme_blocks.py;
`python -m tests.readme_blocks --update` regenerates them)."""

from __future__ import annotations

import pytest

from tests.readme_blocks import COMMANDS, README, blocks, run_code, shown, shown_code


def test_every_checked_command_is_shown_in_the_readme():
    assert set(blocks(README.read_text())) == set(COMMANDS)


@pytest.mark.parametrize("command", COMMANDS)
def test_a_shown_output_is_what_the_command_prints(command):
    text = README.read_text()
    expected, tail = shown(text, command)
    printed, code = run_code(command)
    output = printed.split("\n")
    if tail:
        output = output[-len(expected) :]
    assert output == expected, (
        f"the README's output of `{command}` drifted: "
        "run `.venv/bin/python -m tests.readme_blocks --update`"
    )
    if shown_code(text, command) is not None:
        assert code == shown_code(text, command)

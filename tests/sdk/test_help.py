"""--help says the default of every flag that has one a user would ask about."""

from __future__ import annotations

import re

import pytest

from rigspace.sdk.cli import main


@pytest.mark.parametrize(
    ("command", "flag", "default"),
    [
        ("train", "--preset", "the default"),
        ("render", "--resolution", "default 640x360"),
        ("capture", "--frames-per-item", "default 16"),
        ("capture", "--samples", "default 2"),
        ("capture", "--renderer", "default auto"),
    ],
)
def test_help_shows_the_default(capsys, command, flag, default):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps at the terminal width
    entry = re.search(rf"{re.escape(flag)} [A-Z_x]+ (.*?)(?= --[a-z]|$)", text)
    assert entry and default in entry.group(1), entry and entry.group(1)

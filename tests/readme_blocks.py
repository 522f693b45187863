"""The README's shown outputs, kept true mechanically: the cheap, deterministic commands it
shows are run and their output compared with the README (tests/test_readme.py), and

    .venv/bin/python -m tests.readme_blocks --update

rewrites those blocks from real runs. A block is a fenced block whose first line is
`$ rigspace ...` (a command listed in COMMANDS) and whose output is the command's stdout,
with the repository's path left out; a block whose second line is `...` shows the output's
last lines only; one that ends in `$ echo $?` and a number shows the exit code too. Paths
under /tmp/shot in a shown command run in a fresh folder.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
COMMANDS = (
    "rigspace --help",
    "rigspace init samples/assets/CesiumMan/CesiumMan.usdz --out /tmp/shot/shot.usda",
    "rigspace inspect samples/scenes/previs.usda",
    "rigspace inspect tests/fixtures/broken_character.usda",
    "rigspace capture --help",
)
"""Commands the README shows whose output is quick to make and the same on every run."""
SHOT = "/tmp/shot"


def blocks(text: str) -> dict[str, tuple[int, int, bool]]:
    """command -> (first output line, end line, tail only) of each shown block in COMMANDS;
    the end stops before a closing `$ echo $?` and its number."""
    lines = text.split("\n")
    found = {}
    for i, line in enumerate(lines):
        if line == "```" and i + 1 < len(lines) and lines[i + 1].startswith("$ "):
            command = lines[i + 1][2:]
            end = lines.index("```", i + 2)
            if lines[end - 2] == "$ echo $?":
                end -= 2
            if command in COMMANDS:
                tail = i + 2 < end and lines[i + 2] == "..."
                found[command] = (i + 2 + tail, end, tail)
    return found


def shown_code(text: str, command: str) -> int | None:
    """The exit code a block shows (`$ echo $?`), or None."""
    lines = text.split("\n")
    _, end, _ = blocks(text)[command]
    return int(lines[end + 1]) if lines[end] == "$ echo $?" else None


def run(command: str) -> str:
    """The command's stdout as a terminal 80 columns wide shows it, the repository's path
    left out (run_code: with its exit code)."""
    return run_code(command)[0]


def run_code(command: str) -> tuple[str, int]:
    with tempfile.TemporaryDirectory() as tmp:
        args = command.split()[1:]
        args = [a.replace(SHOT, tmp) for a in args]
        env = {**os.environ, "COLUMNS": "80", "PYTHONWARNINGS": "ignore"}
        done = subprocess.run(
            [sys.executable, "-m", "rigspace.sdk", *args],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        out = done.stdout.replace(tmp, SHOT).replace(f"{REPO}/", "")
    return re.sub(r"\n+$", "", out), done.returncode


def shown(text: str, command: str) -> tuple[list[str], bool]:
    first, end, tail = blocks(text)[command]
    return text.split("\n")[first:end], tail


def update(path: Path = README) -> list[str]:
    """Rewrite every shown block from a real run; returns the commands whose output changed."""
    text = path.read_text()
    changed = []
    for command in COMMANDS:
        if command not in blocks(text):
            continue
        lines = text.split("\n")
        first, end, tail = blocks(text)[command]
        output = run(command).split("\n")
        if tail:
            output = output[-(end - first) :]
        if lines[first:end] != output:
            changed.append(command)
            text = "\n".join([*lines[:first], *output, *lines[end:]])
    path.write_text(text)
    return changed


if __name__ == "__main__":
    if "--update" not in sys.argv:
        sys.exit(__doc__)
    for command in update():
        print(f"updated: $ {command}")

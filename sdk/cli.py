"""The `rigspace` command: a thin front door whose subcommands are plugins.

Each subcommand is a `CommandSpec` found through the `rigspace.commands` entry-point
group, so `sdk` never imports the packages that provide them (capture, train,
runtime). A user error (`RigspaceError`) prints one message naming the thing and the
fix and exits 2; anything else is our bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass

from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.plugins import Kind, discover


@dataclass(frozen=True)
class CommandSpec:
    """A `rigspace` subcommand."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    """Runs the command; returns the process exit code."""
    description: str = ""


def time_range(text: str) -> tuple[float, float]:
    """argparse type for A:B, a range of stage time codes (A and B included)."""
    try:
        first, last = (float(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not A:B (time codes)") from None
    return first, last


COMMANDS: Kind[CommandSpec] = Kind("command", "rigspace.commands", CommandSpec)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rigspace",
        description="Rig-space neural characters in USD scenes.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    commands = discover(COMMANDS)
    for spec in commands:
        cmd = sub.add_parser(
            spec.name,
            help=spec.help,
            description=spec.description or spec.help,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        spec.add_arguments(cmd)
        cmd.set_defaults(_run=spec.run)
    for name, why in commands.failed.items():
        print(f"rigspace: warning: command {name!r} is unavailable: {why}", file=sys.stderr)
    return parser


def sigterm_as_interrupt() -> Callable[[], object]:
    """Make SIGTERM stop a command as Ctrl-C does (its KeyboardInterrupt path: what it keeps,
    what it says): what a batch scheduler or `kill` sends, and the only way to stop a command
    started in the background with `&`, which ignores SIGINT. Returns the function that
    restores the previous handler; a no-op off the main thread (signals are the main
    thread's)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    return lambda: signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args))
    except RigspaceError as exc:
        print(f"rigspace {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"rigspace {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader went away (`rigspace inspect --json | head`): not an error of ours.
        # Point stdout at devnull so the interpreter's final flush does not fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


def entrypoint() -> None:
    sys.exit(main())

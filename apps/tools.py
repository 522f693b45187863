"""What the `python -m rigspace.apps.NAME` tools share: how a run ends and what it says."""

from __future__ import annotations

import sys
from collections.abc import Callable

from rigspace.sdk.errors import RigspaceError


def run_tool(prog: str, work: Callable[[], object]) -> int:
    """Run a tool's `work` to its exit status: 0 when it ends, 2 for a RigspaceError (a bad
    flag, file or URL: said in one line, `PROG: error: ...`, on stderr), 130 on Ctrl-C."""
    try:
        work()
    except RigspaceError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 0

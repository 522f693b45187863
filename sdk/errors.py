"""Errors a user can cause: each names the thing that is wrong and how to fix it."""

from __future__ import annotations


class RigspaceError(Exception):
    """A problem with the user's input (scene, flag, file), reported without a traceback.

    `what` names the offending thing, `fix` says what to do about it.
    """

    def __init__(self, what: str, fix: str = "") -> None:
        self.what = what
        self.fix = fix
        super().__init__(f"{what} Fix: {fix}" if fix else what)


class SceneError(RigspaceError):
    """The stage cannot be opened or lacks what the command needs."""


class PluginError(RigspaceError):
    """A plugin failed to load or is declared twice."""

"""What a scene rule is and reports: `Issue`, `ValidatorSpec`, and the commands an error stops.

A rule (`ValidatorSpec.check`) yields Issues for one prim (or, for a stage rule, the
pseudo-root); `rigspace.sdk.validation` runs the rules through USD's UsdValidation for
inspect, and directly for `require_valid` (capture and render).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

from pxr import Usd

from rigspace.sdk.errors import RigspaceError, SceneError

ERROR = "error"
WARNING = "warning"
CAPTURE, RENDER = "capture", "render"
PURPOSES = (CAPTURE, RENDER)
"""The commands that refuse a scene with errors (`require_valid`'s purposes)."""


@dataclass(frozen=True)
class Issue:
    """One finding of a rigspace rule; the prim defaults to the prim being checked."""

    severity: str
    code: str
    message: str
    """What is wrong, then " Fix: " and what to do about it."""
    purposes: tuple[str, ...] | None = None
    """The commands this error stops, or this warning is shown to; None: its rule's
    (ValidatorSpec.purposes)."""
    exception: type[RigspaceError] | None = None
    """The exception `require_valid` raises for it alone (None: the caller's)."""

    def as_error(self, default: type[RigspaceError] = SceneError) -> RigspaceError:
        what, _, fix = self.message.partition(" Fix: ")
        return (self.exception or default)(what, fix)


@dataclass(frozen=True)
class ValidatorSpec:
    """A scene rule: `check(prim)` yields the issues it finds on that prim."""

    name: str
    doc: str
    check: Callable[[Usd.Prim], Iterable[Issue]]
    purposes: tuple[str, ...] = PURPOSES
    """The commands its errors stop (inspect reports every rule)."""
    stage: bool = False
    """Checked once per stage (`check` gets the pseudo-root) instead of once per prim."""


def error(code: str, message: str, **kwargs) -> Issue:
    return Issue(ERROR, code, message, **kwargs)


def warning(code: str, message: str, **kwargs) -> Issue:
    return Issue(WARNING, code, message, **kwargs)

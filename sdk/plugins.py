"""Plugin kinds and their one shared discovery function.

Every kind is a typed spec plus one entry-point group. `discover(kind)` loads the
group's entry points in sorted order; a plugin that fails to import, or exports
something other than its kind's spec, is reported by name in `PluginSet.failed` and
does not break the others. Two plugins with one name are an error.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Generic, Protocol, TypeVar

from rigspace.sdk.errors import PluginError

S = TypeVar("S")


@dataclass(frozen=True)
class Kind(Generic[S]):
    """A plugin kind: the entry-point group its plugins declare and the spec type they export."""

    name: str
    group: str
    spec_type: type[S]


@dataclass
class PluginSet(Generic[S]):
    """The plugins of one kind found in this environment."""

    kind: Kind[S]
    specs: dict[str, S] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    """Plugin name -> why it could not be loaded (the original error, not swallowed)."""

    def __iter__(self) -> Iterator[S]:
        return iter(self.specs.values())

    def __contains__(self, name: object) -> bool:
        return name in self.specs

    def get(self, name: str) -> S:
        """The spec called `name`, or an error naming what exists and why `name` is missing."""
        if name in self.specs:
            return self.specs[name]
        if name in self.failed:
            raise PluginError(
                f"The {self.kind.name} plugin {name!r} failed to load: {self.failed[name]}",
                "install what the error names, or choose another with one of: "
                + ", ".join(sorted(self.specs)),
            )
        raise PluginError(
            f"There is no {self.kind.name} plugin called {name!r}.",
            f"use one of: {', '.join(sorted(self.specs)) or '(none installed)'}",
        )


def _entry_points(group: str) -> list[metadata.EntryPoint]:
    return sorted(metadata.entry_points(group=group), key=lambda ep: ep.name)


def discover(kind: Kind[S], extra: dict[str, Callable[[], Any]] | None = None) -> PluginSet[S]:
    """Load every plugin of `kind`, sorted by name, each isolated from the others' failures.

    `extra` maps names to loaders for plugins that are not installed as entry points
    (tests and scripts registering their own).
    """
    loaders: list[tuple[str, Callable[[], Any]]] = [
        (ep.name, ep.load) for ep in _entry_points(kind.group)
    ]
    loaders += sorted((extra or {}).items())
    found: PluginSet[S] = PluginSet(kind)
    seen: set[str] = set()
    for name, load in loaders:
        if name in seen:
            raise PluginError(
                f"Two {kind.name} plugins are called {name!r} (entry-point group {kind.group}).",
                "uninstall one of the packages that declare it, or rename one.",
            )
        seen.add(name)
        try:
            spec = load()
        except Exception as exc:  # an isolated plugin failure: report it, keep the others
            found.failed[name] = f"{type(exc).__name__}: {exc}"
            continue
        if not isinstance(spec, kind.spec_type):
            found.failed[name] = (
                f"exports {type(spec).__name__}, expected a {kind.spec_type.__name__}"
            )
            continue
        found.specs[name] = spec
    return found


class LiveSource(Protocol):
    """What a live-source plugin's factory returns: rigspace.runtime.live.transports.Source,
    the base of every built-in source, has these (docs/live.md, "Sources")."""

    name: str
    """The binding's name."""
    url: str
    bones: tuple[str, ...]
    """The names of the bones its frames index (a frame's `indices` point into these)."""
    space: str
    """"local", "world" or "additive": how its rotations are meant."""

    def start(self, buffer: Any) -> None:
        """Open what it needs on the caller's thread (a port in use fails here), then push
        frames into `buffer` (rigspace.runtime.live.buffer.LiveBuffer) from its own thread."""
        ...

    def stop(self, timeout: float = 2.0) -> None:
        """Stop receiving and release the port, device or file."""
        ...

    def counters(self, now: float | None = None) -> Any:
        """Its health for the frame's report (rigspace.runtime.live.buffer.BindingCounters)."""
        ...


@dataclass(frozen=True)
class SourceSpec:
    """What a live-source plugin exports (entry-point group `rigspace.sources`).

    Chosen by the URL's scheme, like pyserial's `serial_for_url`: `factory(url, name)` opens
    the source that `url` names for the binding called `name` (options travel in the URL query).
    """

    scheme: str
    """The URL scheme this plugin handles, e.g. "vmc" or "bvh+tcp"."""
    factory: Callable[[str, str], LiveSource]
    """(url, binding name) -> the source (a LiveSource: start(buffer), stop(), counters())."""
    doc: str
    """One line for `rigspace live --help` and error messages: the URL form and what it reads."""


SOURCES: Kind[SourceSpec] = Kind("source", "rigspace.sources", SourceSpec)
"""Live sources, keyed by URL scheme (docs/live.md)."""

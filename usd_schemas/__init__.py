"""The rigspace USD schema plugin (codeless) and its registration.

`plugin_path()` needs no pxr, so host applications can put it on PXR_PLUGINPATH_NAME
before USD starts. `ensure_registered()` registers the plugin with a running USD and
checks that USD's schema registry knows our types; it runs on `import rigspace.sdk`.
"""

from __future__ import annotations

from pathlib import Path

PLUGIN_NAME = "rigspace"
NEURAL_CHARACTER = "RigspaceNeuralCharacter"
CAPTURE_RING_API = "RigspaceCaptureRingAPI"
LIVE_BINDING_API = "RigspaceLiveBindingAPI"
LIVE_NAMESPACE = "rigspace:live"
REGION_API = "RigspaceRegionAPI"
REGION_NAMESPACE = "rigspace:region"
POINT_CACHE_API = "RigspacePointCacheAPI"
CONTROL_API = "RigspaceControlAPI"
CONTROL_NAMESPACE = "rigspace:control"

__all__ = [
    "CAPTURE_RING_API",
    "CONTROL_API",
    "CONTROL_NAMESPACE",
    "LIVE_BINDING_API",
    "LIVE_NAMESPACE",
    "NEURAL_CHARACTER",
    "PLUGIN_NAME",
    "POINT_CACHE_API",
    "REGION_API",
    "REGION_NAMESPACE",
    "SchemaRegistrationError",
    "ensure_registered",
    "plugin_path",
]


class SchemaRegistrationError(RuntimeError):
    """USD's schema registry was built before the rigspace plugin was registered."""


def plugin_path() -> str:
    """The folder holding plugInfo.json, for PXR_PLUGINPATH_NAME (imports no pxr)."""
    return str(Path(__file__).resolve().parent)


_registered = False


def ensure_registered() -> None:
    """Register the schema plugin with USD once; raise if USD can no longer see our types.

    USD builds its schema registry the first time it is needed (a typed DefinePrim,
    Stage.Open of typed prims, Usd.SchemaRegistry()). A plugin registered after that
    is silently ignored, so this checks the result instead of trusting it.
    """
    global _registered
    if _registered:
        return
    from pxr import Plug, Usd

    registry = Plug.Registry()
    if registry.GetPluginWithName(PLUGIN_NAME) is None:
        registry.RegisterPlugins(plugin_path())
    if registry.GetPluginWithName(PLUGIN_NAME) is None:
        raise SchemaRegistrationError(
            f"USD did not load the rigspace schema plugin from {plugin_path()}: "
            "its plugInfo.json is missing or unreadable. Reinstall rigspace."
        )
    if Usd.SchemaRegistry().FindConcretePrimDefinition(NEURAL_CHARACTER) is None:
        raise SchemaRegistrationError(
            "USD's schema registry was built before rigspace registered its schemas, so "
            f"{NEURAL_CHARACTER} and the rigspace APIs are unknown to this process. Fix: "
            "import rigspace (any rigspace module) before opening stages or defining typed "
            f"prims, or set PXR_PLUGINPATH_NAME={plugin_path()} before starting the host "
            "application."
        )
    _registered = True

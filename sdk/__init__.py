"""Public API of rigspace for scripts and plugin authors: rig and camera math, stage helpers,
plugin kinds and their discovery, config types, and the `rigspace` CLI front door.

Importing any rigspace package that touches USD registers the rigspace schema plugin
(`rigspace.usd_schemas.ensure_registered`), which must happen before USD builds its
schema registry. Without usd-core the USD-free modules (the network, the predictors, the
GPU check) still import; the others fail on their own `from pxr import`.
"""

from importlib.util import find_spec

from rigspace.usd_schemas import ensure_registered

if find_spec("pxr") is not None:  # without usd-core (a GPU box's check) nothing USD can load
    ensure_registered()

from rigspace.sdk.errors import RigspaceError

__all__ = ["RigspaceError", "ensure_registered"]

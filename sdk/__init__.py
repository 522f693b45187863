"""Public API of rigspace for scripts and plugin authors: rig and camera math, stage helpers,
plugin kinds and their discovery, config types, and the `rigspace` CLI front door.

Importing any rigspace package that touches USD registers the rigspace schema plugin
(`rigspace.usd_schemas.ensure_registered`), which must happen before USD builds its
schema registry.
"""

from rigspace.usd_schemas import ensure_registered

ensure_registered()

from rigspace.sdk.errors import RigspaceError  # noqa: E402

__all__ = ["RigspaceError", "ensure_registered"]

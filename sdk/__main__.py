"""`python -m rigspace.sdk` runs the `rigspace` command (for environments without the script)."""

from rigspace.sdk.cli import entrypoint

entrypoint()

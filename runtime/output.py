"""Frame EXRs with named channels, so Nuke, OpenImageIO and others pick them up by name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from rigspace.sdk.exr import write_channels

CHANNELS = ("R", "G", "B", "A", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z")
"""R,G,B,A: lit beauty premultiplied by A (coverage); albedo.*: premultiplied albedo;
N.*: camera-space normals; Z: camera depth along -Z in scene units, +inf where empty."""


def write_frame_exr(path: str | Path, frame) -> None:
    """Write a runtime Frame as one EXR (float16 colour and normals, float32 Z), atomically."""
    maps = frame.maps
    pixels = np.concatenate(
        [frame.beauty, maps.mask[..., None], maps.albedo, maps.normal, maps.depth[..., None]],
        axis=-1,
    )
    write_channels(path, pixels, CHANNELS, (oiio.HALF,) * 10 + (oiio.FLOAT,))

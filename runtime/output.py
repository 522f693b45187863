"""Frame EXRs with named channels, so Nuke, OpenImageIO and others pick them up by name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from rigspace.sdk.exr import write_channels

CHANNELS = ("R", "G", "B", "A", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z")
"""R,G,B,A: lit beauty premultiplied by A (coverage); albedo.*: premultiplied albedo;
N.*: camera-space normals; Z: camera depth along -Z in scene units, +inf where empty."""


AOV_CHANNELS = {
    "beauty": ("R", "G", "B", "A"),
    "mask": ("A",),
    "albedo": ("albedo.R", "albedo.G", "albedo.B"),
    "normal": ("N.X", "N.Y", "N.Z"),
    "depth": ("Z",),
}


def write_frame_exr(path: str | Path, frame, aovs: tuple[str, ...] = tuple(AOV_CHANNELS)) -> None:
    """Write a runtime Frame's AOVs as one EXR (float16 colour and normals, float32 Z),
    atomically; the channels keep CHANNELS' order."""
    maps = frame.maps
    pixels = np.concatenate(
        [frame.beauty, maps.mask[..., None], maps.albedo, maps.normal, maps.depth[..., None]],
        axis=-1,
    )
    wanted = {c for aov in aovs for c in AOV_CHANNELS[aov]}
    keep = [k for k, c in enumerate(CHANNELS) if c in wanted]
    formats = tuple(oiio.FLOAT if CHANNELS[k] == "Z" else oiio.HALF for k in keep)
    write_channels(path, pixels[..., keep], tuple(CHANNELS[k] for k in keep), formats)

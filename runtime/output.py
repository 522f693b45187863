"""Frame EXRs with named channels, so Nuke, OpenImageIO and others pick them up by name."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from rigspace.capture.exr import COMPRESSION, DATE_TIME, ExrError

CHANNELS = ("R", "G", "B", "A", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z")
"""R,G,B,A: lit beauty premultiplied by A (coverage); albedo.*: premultiplied albedo;
N.*: camera-space normals; Z: camera depth along -Z in scene units, +inf where empty."""


def write_frame_exr(path: str | Path, frame) -> None:
    """Write a runtime Frame as one EXR (float16 colour and normals, float32 Z), atomically."""
    path = Path(path)
    maps = frame.maps
    pixels = np.ascontiguousarray(
        np.concatenate(
            [frame.beauty, maps.mask[..., None], maps.albedo, maps.normal, maps.depth[..., None]],
            axis=-1,
        ),
        dtype=np.float32,
    )
    h, w = pixels.shape[:2]
    spec = oiio.ImageSpec(w, h, len(CHANNELS), oiio.FLOAT)
    spec.channelnames = CHANNELS
    spec.channelformats = (oiio.HALF,) * 10 + (oiio.FLOAT,)
    spec.alpha_channel = CHANNELS.index("A")
    spec.z_channel = CHANNELS.index("Z")
    spec.attribute("compression", COMPRESSION)
    spec.attribute("DateTime", DATE_TIME)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.exr")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None or not out.open(str(tmp), spec):
        raise ExrError(f"cannot write {path}: {oiio.geterror()}")
    ok = out.write_image(pixels)
    error = out.geterror()
    out.close()
    if not ok:
        tmp.unlink(missing_ok=True)
        raise ExrError(f"cannot write {path}: {error}")
    os.replace(tmp, path)

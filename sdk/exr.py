"""Multi-channel EXRs named so VFX tools read them: R,G,B,A, Z, N.X/N.Y/N.Z (capture and runtime).

R,G,B = albedo premultiplied by coverage, A = mask (coverage), Z = camera-space depth
along -Z in scene units (+inf where empty), N = camera-space unit normals. Channel
formats, measured (docs/capture.md): half for colour, alpha and normals (error below 3e-4,
under 8-bit quantisation and 0.03 degrees) and float32 for Z (half would lose 0.25 units
at 400 units away). zip compression: byte-identical output for identical input (piz is
not), which is what makes resumed and sharded datasets checksum-equal. Channels are read
back by name, since OpenImageIO may reorder them.

A sample of a textured character also holds its texture AOVs (sdk/charts.py): uv.U, uv.V
the visible surface's USD st (float32: a 4K texture needs 1/4096, and UDIM coordinates reach
10) and chart, its texture chart (float32 integer; 0 where there is none).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from rigspace.sdk.files import replacing
from rigspace.sdk.render import Maps

CHANNELS = ("R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z")
FORMATS = (oiio.HALF,) * 4 + (oiio.FLOAT,) + (oiio.HALF,) * 3
TEXTURE_CHANNELS = ("uv.U", "uv.V", "chart")
TEXTURE_FORMATS = (oiio.FLOAT,) * 3
COMPRESSION = "zip"
DATE_TIME = "1980:01:01 00:00:00"
"""OpenImageIO stamps the write time into DateTime unless one is set; a fixed value (the
reproducible-build convention) keeps a re-rendered sample byte-identical."""


class ExrError(OSError):
    """An EXR that cannot be written or read back."""


def pack(maps: Maps) -> np.ndarray:
    """(H, W, 8) float32 pixels in CHANNELS order (then TEXTURE_CHANNELS when maps has them)."""
    parts = [maps.albedo, maps.mask[..., None], maps.depth[..., None], maps.normal]
    if maps.uv is not None and maps.chart is not None:
        parts += [maps.uv, maps.chart[..., None].astype(np.float32)]
    return np.ascontiguousarray(np.concatenate(parts, axis=-1), dtype=np.float32)


def write_channels(
    path: str | Path,
    pixels: np.ndarray,
    channels: tuple[str, ...],
    formats: tuple,
    attributes: dict[str, str | float] | None = None,
) -> None:
    """Write (H, W, C) float pixels as named channels, atomically (temporary file, rename)."""
    path = Path(path)
    pixels = np.ascontiguousarray(pixels, dtype=np.float32)
    height, width = pixels.shape[:2]
    spec = oiio.ImageSpec(width, height, len(channels), oiio.FLOAT)
    spec.channelnames = channels
    spec.channelformats = formats
    if "A" in channels:
        spec.alpha_channel = channels.index("A")
    if "Z" in channels:
        spec.z_channel = channels.index("Z")
    spec.attribute("compression", COMPRESSION)
    spec.attribute("DateTime", DATE_TIME)
    for key, value in (attributes or {}).items():
        spec.attribute(f"rigspace:{key}", value)
    # Not fsynced (durable=False): a capture or a render writes thousands; a capture's work
    # item record, written durably after its samples, holds their sha256 (resume redoes any lost).
    with replacing(path, ".exr", durable=False) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise ExrError(f"cannot write {path}: {oiio.geterror()}")
        # write_image fails quietly on bad input (DESIGN.md): check its result.
        ok = out.write_image(pixels)
        error = out.geterror()
        out.close()
        if not ok:
            raise ExrError(f"cannot write {path}: {error}")


def write_exr(
    path: str | Path, maps: Maps, attributes: dict[str, str | float] | None = None
) -> None:
    """Write a sample's maps (CHANNELS, FORMATS; TEXTURE_CHANNELS too when the maps have
    texture AOVs) to `path` atomically."""
    textured = maps.uv is not None and maps.chart is not None
    channels = CHANNELS + TEXTURE_CHANNELS if textured else CHANNELS
    formats = FORMATS + TEXTURE_FORMATS if textured else FORMATS
    write_channels(path, pack(maps), channels, formats, attributes)


def read_exr(path: str | Path) -> Maps:
    """Read a sample EXR back into Maps, mapping channels by name."""
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise ExrError(f"cannot read {path}: {oiio.geterror()}")
    try:
        names = list(image.spec().channelnames)
        pixels = image.read_image(oiio.FLOAT)
    finally:
        image.close()
    missing = [c for c in CHANNELS if c not in names]
    if pixels is None or missing:
        raise ExrError(f"{path} is not a rigspace sample: missing channels {missing}")
    pixels = np.asarray(pixels, dtype=np.float32)

    def channel(name: str) -> np.ndarray:
        return pixels[..., names.index(name)]

    maps = Maps(
        albedo=np.stack([channel(c) for c in ("R", "G", "B")], axis=-1),
        normal=np.stack([channel(c) for c in ("N.X", "N.Y", "N.Z")], axis=-1),
        depth=channel("Z"),
        mask=channel("A"),
    )
    if all(c in names for c in TEXTURE_CHANNELS):
        maps.uv = np.stack([channel("uv.U"), channel("uv.V")], axis=-1)
        maps.chart = np.rint(channel("chart")).astype(np.int32)
    return maps

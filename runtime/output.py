"""Frame outputs: EXRs with named channels (Nuke, OpenImageIO and others pick them up by
name) and an H.264 mp4 that browsers play."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Final

import numpy as np
import OpenImageIO as oiio

from rigspace.sdk.exr import write_channels

CHANNELS = (
    *("R", "G", "B", "A", "mask.A"),
    *("albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "Z"),
)
"""R,G,B,A: lit beauty premultiplied by A (1 where a DomeLight fills the background, else
the coverage); mask.A: the coverage of prims and characters, whatever the background;
albedo.*: premultiplied albedo; N.*: camera-space normals; Z: camera depth along -Z in
scene units, +inf where empty."""


AOV_CHANNELS = {
    "beauty": ("R", "G", "B", "A"),
    "mask": ("mask.A",),
    "albedo": ("albedo.R", "albedo.G", "albedo.B"),
    "normal": ("N.X", "N.Y", "N.Z"),
    "depth": ("Z",),
}


def write_frame_exr(path: str | Path, frame, aovs: tuple[str, ...] = tuple(AOV_CHANNELS)) -> None:
    """Write a runtime Frame's AOVs as one EXR (float16 colour and normals, float32 Z),
    atomically; the channels keep CHANNELS' order."""
    maps = frame.maps
    pixels = np.concatenate(
        [
            *(frame.beauty, frame.alpha[..., None], maps.mask[..., None]),
            *(maps.albedo, maps.normal, maps.depth[..., None]),
        ],
        axis=-1,
    )
    wanted = {c for aov in aovs for c in AOV_CHANNELS[aov]}
    keep = [k for k, c in enumerate(CHANNELS) if c in wanted]
    formats = tuple(oiio.FLOAT if CHANNELS[k] == "Z" else oiio.HALF for k in keep)
    write_channels(path, pixels[..., keep], tuple(CHANNELS[k] for k in keep), formats)


VIDEO_CODEC: Final = "libx264"
"""H.264 in yuv420p: what browsers, players and editors all decode (mp4v does not play in
browsers). PyAV's wheel bundles FFmpeg with libx264."""
VIDEO_CRF = 18
"""x264's constant rate factor: 18 is visually lossless for rendered frames (23 is x264's
default; each 6 halves or doubles the size)."""


class VideoWriter:
    """Frames (H, W, 3) uint8 RGB into an H.264 mp4, one `write` per frame; `close` flushes.

    yuv420p halves the chroma resolution, so the picture's sides must be even: an odd
    width or height is padded by repeating the last column or row.
    """

    def __init__(self, path: str | Path, width: int, height: int, fps: float) -> None:
        import av

        self.path = Path(path)
        self.size = (width + width % 2, height + height % 2)
        # Frame rates such as 30000/1001 stay exact; the +faststart index lets a browser
        # start playing before the whole file has arrived.
        self._container = av.open(str(self.path), mode="w", options={"movflags": "+faststart"})
        self._stream = self._container.add_stream(
            VIDEO_CODEC, rate=Fraction(fps).limit_denominator(1001)
        )
        self._stream.width, self._stream.height = self.size
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": str(VIDEO_CRF)}
        # FFmpeg opens the file with the header: now, so a bad path fails before any frame.
        self._container.start_encoding()
        self.frames = 0

    def write(self, rgb: np.ndarray) -> None:
        import av

        h, w = rgb.shape[:2]
        pad = ((0, self.size[1] - h), (0, self.size[0] - w), (0, 0))
        if any(p[1] for p in pad):
            rgb = np.pad(rgb, pad, mode="edge")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        self._container.mux(self._stream.encode(frame))
        self.frames += 1

    def close(self) -> None:
        """Flush the encoder's delayed frames and finish the file (the mp4 index)."""
        self._container.mux(self._stream.encode(None))
        self._container.close()

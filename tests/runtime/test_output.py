"""The runtime's outputs: an H.264 mp4 that browsers play, decoded back by FFmpeg (PyAV)."""

from __future__ import annotations

from fractions import Fraction
from types import SimpleNamespace

import av
import numpy as np
import OpenImageIO as oiio

from rigspace.runtime.output import VideoWriter, write_frame_exr

CHROMA_TOLERANCE = 6
"""8-bit levels a flat colour may move through yuv420p and x264 at crf 18 (measured 2)."""


def _decode(path):
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        codec, pix_fmt = stream.codec_context.name, stream.codec_context.pix_fmt
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    return codec, pix_fmt, frames


def test_video_is_h264_yuv420p_with_every_frame(tmp_path):
    path = tmp_path / "clip.mp4"
    # Odd sides on purpose: yuv420p needs even ones, so the writer pads the last column/row.
    colours = [(200, 40, 40), (40, 200, 40), (40, 40, 200), (220, 220, 220)]
    video = VideoWriter(path, 63, 35, fps=3.0)
    for colour in colours:
        image = np.empty((35, 63, 3), np.uint8)
        image[:] = colour
        image[:, :20] = (0, 0, 0)  # a dark band, so a swapped channel or a shift shows
        video.write(image)
    video.close()
    codec, pix_fmt, frames = _decode(path)
    assert codec == "h264" and pix_fmt == "yuv420p"
    assert len(frames) == len(colours) == video.frames
    assert frames[0].shape == (36, 64, 3)
    for frame, colour in zip(frames, colours, strict=True):
        assert np.abs(frame[20, 40].astype(int) - colour).max() <= CHROMA_TOLERANCE
        assert frame[20, 5].max() <= CHROMA_TOLERANCE
        # The padding repeats the picture's edge, not black.
        assert np.abs(frame[35, 63].astype(int) - colour).max() <= CHROMA_TOLERANCE


def test_video_keeps_a_fractional_frame_rate(tmp_path):
    path = tmp_path / "ntsc.mp4"
    video = VideoWriter(path, 32, 32, fps=30000 / 1001)
    for _ in range(3):
        video.write(np.zeros((32, 32, 3), np.uint8))
    video.close()
    with av.open(str(path)) as container:
        assert container.streams.video[0].average_rate == Fraction(30000, 1001)


def test_the_beauty_alpha_is_one_over_a_sky_and_the_mask_stays_the_coverage(tmp_path):
    """With a DomeLight the beauty is opaque (A = 1) while mask.A is still the coverage."""
    h, w = 4, 6
    mask = np.zeros((h, w), np.float32)
    mask[1:3, 2:4] = 1.0
    maps = SimpleNamespace(
        mask=mask,
        albedo=np.zeros((h, w, 3), np.float32),
        normal=np.zeros((h, w, 3), np.float32),
        depth=np.full((h, w), np.inf, np.float32),
    )
    for opaque in (True, False):
        frame = SimpleNamespace(
            beauty=np.full((h, w, 3), 0.5, np.float32),
            maps=maps,
            alpha=np.ones_like(mask) if opaque else mask,
        )
        path = tmp_path / f"opaque_{opaque}.exr"
        write_frame_exr(path, frame, ("beauty", "mask"))
        image = oiio.ImageInput.open(str(path))
        names = list(image.spec().channelnames)
        pixels = image.read_image(oiio.FLOAT)
        image.close()
        assert names == ["R", "G", "B", "A", "mask.A"]
        np.testing.assert_array_equal(pixels[..., names.index("mask.A")], mask)
        expected_alpha = np.ones_like(mask) if opaque else mask
        np.testing.assert_array_equal(pixels[..., names.index("A")], expected_alpha)

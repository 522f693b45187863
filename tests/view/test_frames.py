"""The viewport's frames: maps, the scrub preview, the cache, and JPEG over the wire."""

from __future__ import annotations

import cv2
import numpy as np


def render(viewer, *args):
    """A frame on the viewer's worker thread, where the server renders too."""
    return viewer.worker.submit(viewer.frames.frame, *args).result()


def decode(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def test_preview_then_full_then_the_cache_answers(previs_served):
    viewer, _ = previs_served
    header, data = render(viewer, 777.0, "beauty", "neural", "preview")
    assert header["quality"] == "preview" and header["width"] == 320 and not header["cached"]
    assert decode(data).shape == (180, 320, 3)
    header, full = render(viewer, 777.0, "beauty", "neural", "full")
    assert header["quality"] == "full" and decode(full).shape == (360, 640, 3)
    hero = header["report"]["characters"][0]
    assert hero["path"] == "/World/Hero" and len(hero["region"]) == 4
    assert set(header["report"]["seconds"]) >= {"scene", "network", "composite", "total"}
    again, same = render(viewer, 777.0, "beauty", "neural", "full")
    assert again["cached"] and same == full and again["server_ms"] < header["server_ms"]
    # Once the full frame is known, a preview request gets it (no worse frame for a scrub).
    better, same = render(viewer, 777.0, "beauty", "neural", "preview")
    assert better["quality"] == "full" and same == full


def test_each_map_is_its_own_image(previs_served):
    viewer, _ = previs_served
    images = {
        name: decode(render(viewer, 321.0, name, "neural", "full")[1]).astype(np.int16)
        for name in ("beauty", "albedo", "normal", "depth", "mask")
    }
    for a in images:
        for b in images:
            if a < b:
                assert np.abs(images[a] - images[b]).mean() > 3, (a, b)
    mask = images["mask"]
    assert mask.max() > 200 and mask.min() < 30  # covered and empty pixels
    assert np.abs(mask[..., 0] - mask[..., 2]).max() < 8  # grey


def test_reference_views_side_by_side_and_error():
    from rigspace.apps.view import build
    from tests.view.conftest import PREVIS

    viewer = build(str(PREVIS), resolution=(160, 90), reference=True)
    try:
        images = {
            view: decode(render(viewer, 200.0, "beauty", view, "auto")[1]).astype(np.int16)
            for view in ("neural", "reference", "compare", "error")
        }
    finally:
        viewer.close()
    assert images["neural"].shape == images["reference"].shape == (90, 160, 3)
    assert images["compare"].shape == (90, 320, 3)
    # Side by side: the network's frame on the left, the skinned mesh's on the right.
    assert np.abs(images["compare"][:, :160] - images["neural"]).mean() < 3
    assert np.abs(images["compare"][:, 160:] - images["reference"]).mean() < 3
    # The two differ where the character is, and the error view shows 4x that.
    assert np.abs(images["neural"] - images["reference"]).max() > 20
    assert images["error"].max() > 60 and np.median(images["error"]) < 10

"""The network's frame against the reference, the characters' skinned meshes drawn by an Engine
with `reference=True` (`rigspace render --reference`, the bench's texture part): per character
region, PSNR of the lit beauty and albedo, FLIP against its ceiling, and mask IoU."""

from __future__ import annotations

from pathlib import Path

NOTHING_TO_COMPARE = "nothing to compare"
"""How the reason of a region with no pixel to compare begins (render's summary counts them)."""
MIN_COMPARED_PX = 1.0
"""A billboard narrower than a pixel covers no pixel centre: the region is background in
both images and its PSNR (120 dB, the 1e-12 floor) would say nothing about the network."""


def coverages(engine, truth, time: float) -> dict:
    """Per character path, its own coverage in the network's frame and its skinned mesh's in
    the reference frame (Engine.coverage_of), both last rendered at `time`."""
    return {
        c.path: (engine.coverage_of(c.path, time), truth.coverage_of(c.path, time))
        for c in engine.characters
    }


def compare_with_reference(frame, truth, path: Path, coverage: dict | None = None) -> list[dict]:
    """compare_regions, and an image neural | reference | 4x error at `path`."""
    import cv2
    import numpy as np

    from rigspace.sdk.color import linear_to_srgb

    results = compare_regions(frame, truth, coverage)
    error = np.clip(4 * np.abs(frame.beauty - truth.beauty), 0, 1)
    row = np.concatenate(
        [linear_to_srgb(frame.beauty), linear_to_srgb(truth.beauty), error], axis=1
    )
    cv2.imwrite(str(path), (row * 255 + 0.5).astype(np.uint8)[..., ::-1])
    return results


def compare_regions(frame, truth, coverage: dict | None = None) -> list[dict]:
    """PSNR of each evaluated character's region (lit beauty and albedo) against the reference
    frame, and the IoU of its own coverage against its skinned mesh's in that region
    (`coverage`: per character path, the two (H, W) coverages, `coverages`; both at 0.5).
    A character drawn with regions of its own (the face, a hand: docs/regions.md) also gets
    the same numbers over each region's own square (`regions`), where its network drew."""
    results = []
    for entry in frame.report.characters:
        if "region" not in entry:
            results.append({"path": entry["path"], "psnr": None, "reason": entry.get("reason", "")})
            continue
        if entry["size_px"] < MIN_COMPARED_PX:
            results.append(
                {
                    "path": entry["path"],
                    "region": entry["region"],
                    "psnr": None,
                    "albedo_psnr": None,
                    "reason": f"{NOTHING_TO_COMPARE}: its billboard is {entry['size_px']:g} px "
                    "across, under a pixel",
                }
            )
            continue
        pair = (coverage or {}).get(entry["path"], (None, None))
        result = {"path": entry["path"], **_compared(frame, truth, entry, pair)}
        drawn = [r for r in entry.get("regions", ()) if "region" in r]
        if drawn:
            result["regions"] = [
                {"name": r["name"], **_compared(frame, truth, r, pair)} for r in drawn
            ]
        results.append(result)
    return results


def _compared(frame, truth, entry: dict, coverage: tuple) -> dict:
    """The numbers of one rectangle (a character's or a region's report entry `region`):
    beauty and albedo PSNR, FLIP and its ceiling, and the mask IoU of the two coverages
    (`coverage`: the network's and the mesh's, (H, W); None: not measured)."""
    import numpy as np

    x, y, w, h = entry["region"]
    region = np.s_[y : y + h, x : x + w]
    result = {
        "region": entry["region"],
        "psnr": _psnr(frame.beauty[region], truth.beauty[region]),
        "albedo_psnr": _psnr(frame.maps.albedo[region], truth.maps.albedo[region]),
        **region_flip(frame.beauty[region], truth.beauty[region], entry),
    }
    neural, mesh = coverage
    if neural is not None and mesh is not None:
        a, b = neural[region] >= 0.5, mesh[region] >= 0.5
        union = int(np.logical_or(a, b).sum())
        result["mask_iou"] = float(np.logical_and(a, b).sum() / union) if union else None
    return result


def region_flip(beauty, truth, entry: dict) -> dict:
    """FLIP of a character's region (rigspace.sdk.flip: its sRGB beauty against the
    reference's), and the ceiling it is measured against: the reference's region squeezed to
    the network's level (its billboard's size_px drawn at `level` pixels) and stretched back,
    what the best image of the network's size would score (0 when the level is not below the
    size on screen)."""
    from rigspace.sdk.flip import mean_flip, squeezed

    factor = float(entry.get("size_px", 0.0)) / max(int(entry.get("level") or 1), 1)
    ceiling = mean_flip(squeezed(truth, factor), truth) if factor > 1.0 else 0.0
    return {"flip": mean_flip(beauty, truth), "flip_ceiling": ceiling}


def _psnr(a, b) -> float:
    """PSNR in dB of two images clipped to [0, 1] (peak 1)."""
    import numpy as np

    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return float(10 * np.log10(1 / max(mse, 1e-12)))

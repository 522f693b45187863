"""A contact sheet of a dataset: a few samples, one per row, as albedo | normal | depth | mask."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rigspace.capture import dataset as ds
from rigspace.sdk.color import linear_to_srgb
from rigspace.sdk.exr import read_exr
from rigspace.sdk.files import write_atomic
from rigspace.sdk.render import Maps

ROWS = 6
BACKGROUND = 0.08
"""Linear grey behind the premultiplied albedo, dark enough that the silhouette reads."""
LABEL_HEIGHT = 18


def map_tiles(maps: Maps) -> list[np.ndarray]:
    """The four maps of a sample as 8-bit BGR tiles."""
    mask = maps.mask[..., None]
    albedo = linear_to_srgb(maps.albedo + BACKGROUND * (1 - mask))
    normal = np.where(mask > 0, maps.normal * 0.5 + 0.5, BACKGROUND)
    finite = np.isfinite(maps.depth)
    depth8 = np.zeros(maps.depth.shape, np.uint8)
    if finite.any():
        near, far = maps.depth[finite].min(), maps.depth[finite].max()
        scaled = 1 - (maps.depth - near) / max(far - near, 1e-6)  # near is bright
        depth8 = np.where(finite, 30 + 225 * scaled, 0).astype(np.uint8)
    depth = cv2.applyColorMap(depth8, cv2.COLORMAP_TURBO)
    depth[~finite] = 0
    tiles = [albedo, normal, np.repeat(maps.mask[..., None], 3, axis=2)]
    as8 = [(np.clip(t, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1] for t in tiles]
    return [as8[0], as8[1], depth, as8[2]]


def contact_sheet(folder: Path, rows: int = ROWS, scale: int = 2) -> np.ndarray:
    """A BGR image of up to `rows` samples spread over the dataset, one per row."""
    with np.load(folder / ds.PARAMS_FILE, allow_pickle=False) as table:
        paths, splits = table["path"], table["split"]
    order = np.flatnonzero(splits == 0) if np.any(splits == 0) else np.arange(len(paths))
    picks = order[np.linspace(0, len(order) - 1, min(rows, len(order))).astype(int)]
    lines = []
    for index in picks:
        tiles = map_tiles(read_exr(folder / str(paths[index])))
        row = np.concatenate(
            [
                cv2.resize(t, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
                for t in tiles
            ],
            axis=1,
        )
        label = np.zeros((LABEL_HEIGHT, row.shape[1], 3), np.uint8)
        text = f"{paths[index]}  ({ds.SPLITS[int(splits[index])]})"
        cv2.putText(
            label, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (220, 220, 220), 1, cv2.LINE_AA
        )
        lines += [label, row]
    header = np.zeros((LABEL_HEIGHT, lines[1].shape[1], 3), np.uint8)
    width = lines[1].shape[1] // 4
    for k, name in enumerate(("albedo", "normal (camera)", "depth", "mask")):
        cv2.putText(
            header,
            name,
            (k * width + 4, 13),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
    return np.concatenate([header, *lines], axis=0)


def write_contact_sheet(folder: Path) -> Path:
    path = folder / ds.CONTACT_SHEET
    ok, png = cv2.imencode(".png", contact_sheet(folder))
    if not ok:
        raise OSError(f"could not encode {path}")
    write_atomic(path, png.tobytes())
    return path

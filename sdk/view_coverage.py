"""The views of its look-at joint a network learned, and how far a frame's view is from them.

A network draws its look-at joint as its training cameras saw it: the joint's rotation in the
camera's frame (the rig input's rows for that joint) over the ring's views and the clips'
poses. Where a shot's camera sees the joint from outside those (the film character's head in
the held-out wave clip, tilted about the line of sight as no trained clip tilts it), the
network draws a guess: a frontal, average face. The export keeps those rotations
(`views.npy`, its manifest's `views` section); the runtime gives each evaluated body and
region how far its view lies outside them (`novel_view_deg` in the frame's report, and which
way when it is far), and `rigspace render` names a network whose frames were far, and the ring
elevation or the clips that would have covered them (docs/regions.md, "Views a network never
learned").

How far is "outside": the views a network learned surround most of a shot's (between two
ring azimuths, between two elevations, between two poses of a clip: interpolated, as the
held-out views are). A view is novel by how far it lies outside the training views around it:
the distance (degrees, as a rotation in the camera's frame) from it to the convex hull of its
NEIGHBOURS nearest training views, in the tangent space at it; 0 inside. A raised ring
elevation turns the joint's rotation about the camera's X axis by the elevation (positive:
seen from above), so the direction from the hull to the view says "from below" or "from
above"; a Z part is a roll about the line of sight, a Y part a turn beyond the ring's views.
"""

from __future__ import annotations

from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.rotations import ROT6D, decode, quat_from_matrix, quat_multiply

VIEWS_FILE = "views.npy"
MAX_VIEWS = 16384
"""Training rotations a bundle keeps (evenly over its training rows, all of them up to this):
256 KiB. Fewer leave holes a trained view falls into (a quarter of the film face's 12,420
put trained frames of its stretch clip 6-8 deg outside them); a frame's search, where it runs,
costs about 0.5 ms."""
NOVEL_VIEW_DEG = 6.0
"""A frame's view this far (degrees) outside the training views around it is a guess of its
network's. The film face's held-out views lie inside theirs (between the ring's azimuths:
0.7 deg outside at the 95th percentile); the render's frames of the held-out wave clip
7.0-10.4 deg outside, its head rolled as no trained clip rolls it (its image there: a
frontal, average face)."""
NEIGHBOURS = 48
"""Training views around a frame's view whose hull it is measured against."""
WAYS = ("from below", "from above", "turned beyond the ring's views", "rolled")


class ViewCoverageError(RigspaceError):
    """A bundle's views file that cannot be read."""


def joint_rotations(rows: np.ndarray, joint: int) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z) of joint `joint`'s rotation in the camera's frame
    from rig input rows (N, J*6 + B + C; sdk.rotations.rig_inputs)."""
    six = np.asarray(rows, dtype=np.float64)[:, 6 * joint : 6 * joint + 6]
    return quat_from_matrix(decode(six, ROT6D))


@dataclass(frozen=True)
class ViewCoverage:
    """A network's training views of its look-at joint (a bundle's `views` section)."""

    rotations: np.ndarray
    """(N, 4) unit quaternions: the joint's rotation in each kept training camera's frame."""
    joint: int
    """The look-at joint's index in the bundle's joints (its rows in the rig input)."""
    elevations: tuple[float, ...] = ()
    """The capture ring's elevations (degrees), for the advice."""
    held_out: dict[str, float] | None = None
    """How far outside the training views the held-out views lie (median, p95), for scale."""

    def outside(self, rows: np.ndarray) -> tuple[float, str]:
        """Degrees the first rig row's view of the joint lies outside the training views
        around it, and which way (WAYS); 0 and "" inside them (to a few tenths of a degree)
        or where a training view lies within NOVEL_VIEW_DEG (the hull is no further: the
        search is skipped, most frames of a shot)."""
        q = joint_rotations(rows[:1], self.joint)[0]
        dots = self.rotations @ q
        if np.degrees(2 * np.arccos(min(1.0, float(np.abs(dots).max())))) <= NOVEL_VIEW_DEG:
            return 0.0, ""  # the hull is at most as far as its nearest view: not novel
        count = min(NEIGHBOURS, len(dots))
        near = np.argpartition(-np.abs(dots), count - 1)[:count]
        # The neighbours as rotation vectors (degrees) from the view, in the camera's frame.
        turns = quat_multiply(self.rotations[near] * np.sign(dots[near])[:, None], _inverse(q))
        sine = np.linalg.norm(turns[:, 1:], axis=1)
        angle = np.degrees(2 * np.arctan2(sine, turns[:, 0]))
        points = turns[:, 1:] / np.maximum(sine, 1e-12)[:, None] * angle[:, None]
        closest = _nearest_in_hull(points)
        degrees = float(np.linalg.norm(closest))
        return degrees, _way(-closest) if degrees > 1e-6 else ""

    def to_json(self, kept: int, of: int) -> dict[str, Any]:
        return {
            "file": VIEWS_FILE,
            "joint": self.joint,
            "rows": kept,
            "of": of,
            "elevations": list(self.elevations),
            **({"held_out_deg": self.held_out} if self.held_out else {}),
        }


def _inverse(q: np.ndarray) -> np.ndarray:
    return q * [1.0, -1.0, -1.0, -1.0]


def _nearest_in_hull(points: np.ndarray, iterations: int = 64) -> np.ndarray:
    """The point of the convex hull of `points` (K, 3; degrees) nearest the origin, to about
    a tenth of a degree (Frank-Wolfe with an exact line search, stopped once its duality gap
    bounds the error so, or the point is within half a degree of the origin: inside)."""
    x = points[int(np.argmin(np.einsum("ij,ij->i", points, points)))]
    for _ in range(iterations):
        along = points @ x
        k = int(np.argmin(along))
        xx = float(x @ x)
        gap = xx - float(along[k])  # >= |x|^2 - |x*|^2
        if gap <= 0.05 * max(xx, 1.0) or xx <= 0.25:
            break
        d = x - points[k]
        x = x - min(1.0, gap / float(d @ d)) * d
    return x


def _way(beyond: np.ndarray) -> str:
    """Which way a view lies from the training views, `beyond` the rotation vector (camera
    frame) from the nearest of them to it: its largest part (X: seen from below or above, Y:
    turned beyond the ring's views, Z: rolled)."""
    axis = int(np.argmax(np.abs(beyond)))
    if axis == 0:
        return WAYS[0] if beyond[0] < 0 else WAYS[1]
    return WAYS[2] if axis == 1 else WAYS[3]


def build_views(
    train_rows: np.ndarray,
    held_rows: np.ndarray | None,
    joint: int,
    elevations: tuple[float, ...],
) -> tuple[ViewCoverage, int]:
    """The coverage of training rows (at most MAX_VIEWS of them, evenly), with the held-out
    rows' distances to it; and how many training rows there were."""
    every = joint_rotations(train_rows, joint)
    picks = np.unique(np.linspace(0, len(every) - 1, min(MAX_VIEWS, len(every))).astype(int))
    coverage = ViewCoverage(every[picks], joint, tuple(float(e) for e in elevations))
    if held_rows is not None and len(held_rows):
        step = max(1, len(held_rows) // 256)
        distances = [coverage.outside(row[None])[0] for row in held_rows[::step]]
        held = {
            "median": round(float(np.median(distances)), 2),
            "p95": round(float(np.percentile(distances, 95)), 2),
        }
        coverage = ViewCoverage(coverage.rotations, joint, coverage.elevations, held)
    return coverage, len(every)


def views_bytes(coverage: ViewCoverage) -> bytes:
    buffer = BytesIO()
    np.save(buffer, coverage.rotations.astype(np.float32), allow_pickle=False)
    return buffer.getvalue()


def read_views(folder: Path, section: dict[str, Any], joints: int) -> ViewCoverage:
    """A bundle's views (its manifest's `views` section and file), checked: a missing,
    unreadable or malformed file is a ViewCoverageError naming it."""
    path = folder / str(section.get("file", VIEWS_FILE))
    fix = (
        "write it again from the dataset the bundle was trained on (`python -m "
        "rigspace.apps.views BUNDLE DATASET`), or remove the manifest's `views` section (its "
        "frames then report no novel views)."
    )
    try:
        rotations = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ViewCoverageError(
            f"Model bundle {folder}: {path.name} cannot be read ({exc}).", fix
        ) from None
    joint = section.get("joint")
    if not isinstance(joint, int) or not 0 <= joint < joints or not _quaternions(rotations):
        raise ViewCoverageError(
            f"Model bundle {folder}: {path.name} holds {rotations.shape} {rotations.dtype} "
            f"for joint {joint!r}, not (N, 4) finite quaternions of one of its {joints} joints.",
            fix,
        )
    unit = rotations.astype(np.float64)
    unit /= np.maximum(np.linalg.norm(unit, axis=1, keepdims=True), 1e-12)
    held = section.get("held_out_deg")
    return ViewCoverage(
        unit,
        joint,
        tuple(float(e) for e in section.get("elevations") or ()),
        dict(held) if isinstance(held, dict) else None,
    )


def _quaternions(a: np.ndarray) -> bool:
    shaped = a.ndim == 2 and a.shape[1] == 4 and len(a) > 0
    return shaped and np.issubdtype(a.dtype, np.floating) and bool(np.all(np.isfinite(a)))


def advice(way: str, worst: float, elevations: tuple[float, ...], attribute: str) -> str:
    """What would have covered views `worst` degrees beyond the training ones, `way` from
    them: a lower or higher ring elevation (`attribute`: the ring's elevations attribute), more
    views per ring, or poses that roll the joint."""
    step = 5 * int(np.ceil(worst / 5))
    if way in (WAYS[0], WAYS[1]) and elevations:
        lowest, highest = min(elevations), max(elevations)
        extra = lowest - step if way == WAYS[0] else highest + step
        wanted = sorted({*elevations, float(extra)})
        shown = ", ".join(f"{e:g}" for e in wanted)
        return f"author {attribute} = [{shown}] and capture and train it again"
    if way == WAYS[2]:
        return (
            "give its ring more views (viewsPerRing), or clips that turn its joint this far, "
            "and capture and train it again"
        )
    return "capture it in clips that roll its joint this way, and train it again"

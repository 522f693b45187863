"""Numerical stability: adversarial rigs through a model bundle, its outputs' ranges, int8 drift.

    stress(BundleModel(path), n=2000, seed=0, level=16)      # violations, q vs -q, timing
    drift(BundleModel(path), BundleModel(path, "int8"), rigs, level=128)
    python -m rigspace.apps.stability                       # quick: 2,000 rigs, then drift
    python -m rigspace.apps.stability --long                # 100,000 rigs at level 16

The generators give (n, J, 4) quaternions (w, x, y, z) for a skeleton of J joints, seeded
through a numpy Generator:

- `haar`: uniform rotations (the Haar measure on SO(3): a normalised 4D Gaussian);
- `half_turn`: exact 180-degree turns about uniform axes (w = 0: the trace of the matrix is
  -1, where q and -q both satisfy the w >= 0 canonical form and naive axis-angle code fails);
- `near_gimbal`: intrinsic X-Y-Z Euler angles whose middle angle lies within `GIMBAL_WITHIN`
  of +-90 degrees, where Euler angles lose a degree of freedom (6D has no such point);
- `scaled`: Haar quaternions times 10^U(-6, 6), not unit;
- `mixed`: every joint from any of the above.

Non-unit quaternions are normalised, not rejected, because that is what
`sdk/rotations.matrix_from_quat` does (q / max(|q|, 1e-12)): s q and q give the same rig
parameters for every s the generators draw (NaN and Inf are `BundleModel.check_rig`'s to
reject, with the joint's name). Poses read from a SkelAnimation take another path: UsdSkel
builds their matrices as if the quaternions were unit, so a non-unit one there gives a
sheared, scaled matrix, which `rig_parameters` turns into a different rotation (not
exercised here). Here quaternions enter the rig through `matrix_from_quat` and
`rig_parameters` with a uniformly random camera frame per rig, as the runtime's virtual
camera C R enters it. `stress` runs them through the network in batches whose last eighth
repeats the batch's first rigs as -q: q and -q are one rotation, so their outputs must agree.

The long mode runs 100,000 rigs at level 16, the smallest level with an upsampling block
(level 8 is the trunk's 8x8 features through a 1x1 head alone). Measured on 2 shared cores:
2,000 rigs at level 16 in 2.6 s (1.2 ms a rig in the network, 0.1 ms making it), so the
long mode takes about two to three minutes there.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.sdk.model import BundleModel
from rigspace.sdk.rotations import matrix_from_quat, quat_multiply, rig_parameters
from rigspace.train.metrics import MASK_THRESHOLD, mask_iou, psnr

KINDS = ("haar", "half_turn", "near_gimbal", "scaled", "mixed")
GIMBAL_WITHIN = 1e-6
"""Radians between the near-gimbal middle Euler angle and +-90 degrees."""
SCALE_DECADES = 6
"""Non-unit quaternions are scaled by 10^U(-SCALE_DECADES, SCALE_DECADES)."""
COVERAGE = ("mask", "alpha")
"""Maps documented as coverage in [0, 1] (alpha: the albedo branch's, bundle format 2)."""
UNIT_RANGE = (*COVERAGE, "albedo")
"""Maps documented in [0, 1] (albedo: sigmoid, premultiplied)."""
NEGATED_FRACTION = 8
"""One rig in this many of a stress batch is the -q twin of another in the same batch."""
LONG_RIGS = 100_000
LONG_LEVEL = 16
ROOT = Path(__file__).resolve().parents[1]
SAMPLE_MODEL = ROOT / "samples" / "models" / "sample"
PREVIS = ROOT / "samples" / "scenes" / "previs.usda"


@dataclass(frozen=True)
class Tolerance:
    """How far a map may be from its documented range before it counts as a violation."""

    unit_normal: float = 1e-3
    """| |n| - 1 | where the mask is set. F.normalize in the graph: measured 1.4e-7 in fp32
    and in int8, except where the int8 head rounds all three components to its zero point
    and the normal comes out zero (|n| - 1 = -1), which this counts."""
    unit_range: float = 0.0
    """Slack outside [0, 1] for coverage and albedo: none, they come out of a sigmoid."""


TOLERANCE = Tolerance()


# --- generators: (n, J, 4) quaternions (w, x, y, z) ------------------------------------------


def haar(rng: np.random.Generator, n: int, joints: int) -> np.ndarray:
    """Uniformly random rotations: a 4D standard Gaussian, normalised (Shoemake 1992)."""
    q = rng.standard_normal((n, joints, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def half_turn(rng: np.random.Generator, n: int, joints: int) -> np.ndarray:
    """180-degree turns about uniform axes: w = 0 exactly."""
    axis = haar(rng, n, joints)[..., 1:]
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    return np.concatenate([np.zeros((n, joints, 1)), axis], axis=-1)


def _axis_angle(axis: int, angle: np.ndarray) -> np.ndarray:
    """Quaternions of turns by `angle` about coordinate axis 0 (X), 1 (Y) or 2 (Z)."""
    q = np.zeros((*angle.shape, 4))
    q[..., 0] = np.cos(angle / 2)
    q[..., 1 + axis] = np.sin(angle / 2)
    return q


def euler_xyz(alpha: np.ndarray, beta: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Quaternions of intrinsic X-Y-Z Euler angles: R = Rx(alpha) Ry(beta) Rz(gamma)."""
    return quat_multiply(
        quat_multiply(_axis_angle(0, alpha), _axis_angle(1, beta)), _axis_angle(2, gamma)
    )


def near_gimbal(
    rng: np.random.Generator, n: int, joints: int, within: float = GIMBAL_WITHIN
) -> np.ndarray:
    """Euler X-Y-Z rotations whose middle angle is within `within` radians of +-90 degrees."""
    shape = (n, joints)
    beta = rng.choice([-np.pi / 2, np.pi / 2], size=shape) + rng.uniform(-within, within, shape)
    alpha, gamma = rng.uniform(-np.pi, np.pi, (2, *shape))
    return euler_xyz(alpha, beta, gamma)


def scaled(rng: np.random.Generator, n: int, joints: int) -> np.ndarray:
    """Haar quaternions times 10^U(-6, 6): the same rotations, far from unit length."""
    s = 10.0 ** rng.uniform(-SCALE_DECADES, SCALE_DECADES, (n, joints, 1))
    return haar(rng, n, joints) * s


GENERATORS = {"haar": haar, "half_turn": half_turn, "near_gimbal": near_gimbal, "scaled": scaled}


def generate(kind: str, rng: np.random.Generator, n: int, joints: int) -> np.ndarray:
    """(n, J, 4) quaternions of one of KINDS; `mixed` draws each joint from any other kind."""
    if kind == "mixed":
        each = np.stack([g(rng, n, joints) for g in GENERATORS.values()])
        pick = rng.integers(len(GENERATORS), size=(n, joints))
        return np.take_along_axis(each, pick[None, ..., None], axis=0)[0]
    return GENERATORS[kind](rng, n, joints)


def adversarial(rng: np.random.Generator, n: int, joints: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, J, 4) quaternions and (n,) kind indices into KINDS, the kinds drawn uniformly."""
    kinds = rng.integers(len(KINDS), size=n)
    q = np.empty((n, joints, 4))
    for k, kind in enumerate(KINDS):
        rows = np.flatnonzero(kinds == k)
        q[rows] = generate(kind, rng, len(rows), joints)
    return q, kinds


def camera_frames(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4, 4) rigid camera-to-world transforms: uniform rotations, translations N(0, 100^2)."""
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3] = matrix_from_quat(haar(rng, n, 1)[:, 0])
    m[:, :3, 3] = rng.normal(0.0, 100.0, (n, 3))
    return m


def rigs(quaternions: np.ndarray, cameras: np.ndarray) -> np.ndarray:
    """(n, J*6) float32 rig parameters of (n, J, 4) joint world rotations seen from (n, 4, 4)
    cameras, through sdk/rotations as the runtime computes them (one call per rig)."""
    world = np.tile(np.eye(4), (*quaternions.shape[:2], 1, 1))
    world[..., :3, :3] = matrix_from_quat(quaternions)
    return np.stack([rig_parameters(w, c).reshape(-1) for w, c in zip(world, cameras, strict=True)])


# --- checks ------------------------------------------------------------------------------------


def violations(out: dict[str, np.ndarray], tol: Tolerance = TOLERANCE) -> dict[str, np.ndarray]:
    """Per problem found in a batch of maps (N, C, H, W), which of the N samples have it."""
    found: dict[str, np.ndarray] = {}

    def per_sample(bad: np.ndarray) -> np.ndarray:
        return np.asarray(bad.reshape(bad.shape[0], -1).any(axis=1))

    for name, value in sorted(out.items()):
        finite = np.isfinite(value)
        found[f"{name}: NaN or Inf"] = per_sample(~finite)
        if name in UNIT_RANGE:
            outside = (value < -tol.unit_range) | (value > 1 + tol.unit_range)
            found[f"{name}: outside [0, 1]"] = per_sample(outside & finite)
    if "normal" in out and "mask" in out:
        covered = out["mask"][:, 0] >= MASK_THRESHOLD
        length = np.linalg.norm(out["normal"].astype(np.float64), axis=1)
        unit = np.abs(length - 1) <= tol.unit_normal  # False for NaN as well
        found[f"normal: not unit where mask >= {MASK_THRESHOLD:g}"] = per_sample(covered & ~unit)
    return {problem: rows for problem, rows in found.items() if rows.any()}


# --- stress and drift --------------------------------------------------------------------------


def _rigs_with_twins(
    rng: np.random.Generator, size: int, twins: int, joints: int
) -> tuple[np.ndarray, np.ndarray]:
    """`size` adversarial rigs and their kinds: the last `twins` are the first ones' -q twins,
    seen by the same camera frames."""
    q, kinds = adversarial(rng, size - twins, joints)
    q = np.concatenate([q, -q[:twins]])
    kinds = np.concatenate([kinds, kinds[:twins]])
    cameras = camera_frames(rng, size - twins)
    return rigs(q, np.concatenate([cameras, cameras[:twins]])), kinds


def _count_problems(
    found: dict[str, np.ndarray],
    kinds: np.ndarray,
    problems: Counter[str],
    ran: Counter[str],
    bad_by_kind: Counter[str],
) -> None:
    """Count the rigs that show each problem, and by kind the rigs run and those with any."""
    any_bad = np.zeros(len(kinds), dtype=bool)
    for problem, rows in found.items():
        problems[problem] += int(rows.sum())
        any_bad |= rows
    ran.update(KINDS[k] for k in kinds)
    bad_by_kind.update(KINDS[k] for k in kinds[any_bad])


def _twin_gap(values: np.ndarray, twins: int) -> float:
    """The largest |value(q) - value(-q)| over the batch's first `twins` rigs and their twins."""
    return float(np.abs(values[:twins] - values[len(values) - twins :]).max())


def _widen_ranges(ranges: dict[str, list[float]], out: dict[str, np.ndarray]) -> None:
    """Each map's [lowest, highest] finite value so far, widened by `out`'s."""
    for name, value in out.items():
        finite = value[np.isfinite(value)]
        if finite.size:
            lo, hi = ranges.get(name, [math.inf, -math.inf])
            ranges[name] = [min(lo, float(finite.min())), max(hi, float(finite.max()))]


def stress(
    model: BundleModel,
    n: int = 2000,
    seed: int = 0,
    level: int = 16,
    batch: int = 256,
    tol: Tolerance = TOLERANCE,
) -> dict[str, Any]:
    """Run `n` adversarial rigs (every kind, random camera frames) through `model` at `level`.

    Returns how many rigs of each kind ran and how many showed each problem (see
    `violations`), the largest |output(q) - output(-q)| per map over the -q twins, each
    map's range, and the seconds spent making rigs, in the network and checking.
    """
    rng = np.random.default_rng(seed)
    joints = len(model.joints)
    ran: Counter[str] = Counter()
    problems: Counter[str] = Counter()
    bad_by_kind: Counter[str] = Counter()
    negation: dict[str, float] = {}
    pairs, rig_gap = 0, 0.0
    ranges: dict[str, list[float]] = {}
    seconds = dict.fromkeys(("rigs", "network", "checks"), 0.0)
    for start in range(0, n, batch):
        size = min(batch, n - start)
        twins = size // NEGATED_FRACTION
        t = time.perf_counter()
        rig, kinds = _rigs_with_twins(rng, size, twins, joints)
        seconds["rigs"] += time.perf_counter() - t
        t = time.perf_counter()
        out = model.predict(rig, level)
        seconds["network"] += time.perf_counter() - t
        t = time.perf_counter()
        _count_problems(violations(out, tol), kinds, problems, ran, bad_by_kind)
        if twins:
            pairs += twins
            rig_gap = max(rig_gap, _twin_gap(rig, twins))
            for name, value in out.items():
                negation[name] = max(negation.get(name, 0.0), _twin_gap(value, twins))
        _widen_ranges(ranges, out)
        seconds["checks"] += time.perf_counter() - t
    total = sum(seconds.values())
    return {
        "rigs": n,
        "level": level,
        "batch": batch,
        "seed": seed,
        "precision": model.precision,
        "rigs_by_kind": dict(sorted(ran.items())),
        "violations": dict(sorted(problems.items())),
        "violating_rigs_by_kind": dict(sorted(bad_by_kind.items())),
        "negated_pairs": pairs,
        "negation_max_abs_rig": rig_gap,
        "negation_max_abs": dict(sorted(negation.items())),
        "ranges": dict(sorted(ranges.items())),
        "seconds": {**{k: round(v, 3) for k, v in seconds.items()}, "total": round(total, 3)},
        "rigs_per_second": round(n / total, 1) if total > 0 else math.nan,
        "network_ms_per_rig": round(1e3 * seconds["network"] / max(n, 1), 3),
    }


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between (..., 3) vectors, atan2(|a x b|, a . b): exact near 0, unlike arccos."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def drift(
    fp32_model: BundleModel, int8_model: BundleModel, rigs: np.ndarray, level: int
) -> dict[str, Any]:
    """Per map, how far the int8 graphs' outputs are from the fp32 ones for the same rigs.

    albedo: mean and max |diff| and PSNR (peak 1, all pixels of all rigs, premultiplied as
    stored); coverage (mask, alpha): IoU at 0.5 (mean and worst over the rigs) and mean |diff|;
    depth: mean and max |diff| in the bundle's depth units (offset times depth.scale), over
    the pixels the fp32 mask covers; normal: mean and 95th-percentile angle in degrees over
    those pixels, and how many of them have a zero-length normal in either model (no angle).
    Any other map: mean and max |diff|.
    """
    a = fp32_model.predict(rigs, level)
    b = int8_model.predict(rigs, level)
    covered = a["mask"][:, 0] >= MASK_THRESHOLD if "mask" in a else None
    report: dict[str, Any] = {"rigs": len(rigs), "level": level}
    if covered is not None:
        report["covered_fraction"] = float(covered.mean())
    for name in sorted(a.keys() & b.keys()):
        diff = np.abs(a[name].astype(np.float64) - b[name])
        row: dict[str, Any] = {}
        if name == "depth":
            diff = diff[:, 0] * fp32_model.depth_scale
            diff = diff[covered] if covered is not None else diff
            units = fp32_model.manifest.depth_units
            row["units"] = units
        if name == "normal" and covered is not None:
            n32, n8 = np.moveaxis(a[name], 1, -1)[covered], np.moveaxis(b[name], 1, -1)[covered]
            # A zero-length normal has no angle (atan2(0, 0) would say 0 degrees): counted apart.
            zero = (np.linalg.norm(n32, axis=-1) == 0) | (np.linalg.norm(n8, axis=-1) == 0)
            angle = _angles_deg(n32[~zero], n8[~zero])
            row["mean_deg"] = float(angle.mean()) if angle.size else math.nan
            row["p95_deg"] = float(np.percentile(angle, 95)) if angle.size else math.nan
            row["zero_length_pixels"] = int(zero.sum())
            row["covered_pixels"] = int(covered.sum())
        else:
            row["mean_abs"] = float(diff.mean()) if diff.size else math.nan
            row["max_abs"] = float(diff.max()) if diff.size else math.nan
        if name == "albedo":
            row["psnr_db"] = psnr(b[name], a[name])
        if name in COVERAGE:
            ious = [mask_iou(p, t) for p, t in zip(b[name], a[name], strict=True)]
            row["iou_mean"], row["iou_min"] = float(np.mean(ious)), float(np.min(ious))
        report[name] = row
    return report


# --- in-distribution rigs: the sample scene's animation ----------------------------------------


def animation_rigs(
    scene: str | Path, character: str, model: BundleModel, n: int, seed: int = 0
) -> np.ndarray:
    """(n, J*6) rig parameters of `character`'s animation at random times, seen from cameras
    on a training-like ring (the model's training distance, elevations -10 to 40 degrees)."""
    from rigspace.runtime.character import NeuralCharacter
    from rigspace.sdk.camera import Camera
    from rigspace.sdk.stage import open_stage

    stage = open_stage(scene)
    hero = NeuralCharacter(stage.GetPrimAtPath(character), model)
    first, last = hero.rig.time_range() or (0.0, 0.0)
    rng = np.random.default_rng(seed)
    rows = []
    for t, azimuth, elevation in zip(
        rng.uniform(first, last, n),
        rng.uniform(0, 2 * np.pi, n),
        np.radians(rng.uniform(-10, 40, n)),
        strict=True,
    ):
        world = hero.pose(float(t))
        joint = world[hero.look_at][:3, 3]
        ray = np.array(
            [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
        )  # fmt: skip
        camera = Camera.look_at(
            joint + hero.view.distance * ray,
            joint,
            width=128,
            height=128,
            focal_length=hero.view.focal_length,
            horizontal_aperture=hero.view.horizontal_aperture,
        )
        rows.append(hero.parameters(world, hero.place(world, camera), camera)[0])
    return np.stack(rows)

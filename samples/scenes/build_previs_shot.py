"""Regenerate the previs shot's animation: the camera's look-at rig and the crate's and ball's paths.

    .venv/bin/python samples/scenes/build_previs_shot.py           # rewrite previs.usda's samples
    .venv/bin/python samples/scenes/build_previs_shot.py --check   # exit 1 when they are stale

The camera aims at the hero's pelvis (rigspace.sdk.posing.CharacterRig on the stage's own
animation), smoothed over half a second so it follows the walk and the roll without shaking,
and orbits, dollies and tilts along the keyframes below. Its transform is four ops:
translate:target (the smoothed pelvis), rotateY (orbit), translate:dolly (back and up from
the target by the distance and elevation) and rotateX (minus the elevation), so at every
sample the camera looks exactly at the target. The crate crosses between the camera and the
hero, and the ball rolls behind the hero, each along a straight line across the camera's
view at the moment chosen below. The samples replace the bodies of previs.usda's existing
time-sample blocks; the rest of the file, comments included, is left as it is. The output
depends only on the character's animation and the constants here: running this again
changes nothing.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom

SCENE = Path(__file__).resolve().parent / "previs.usda"
HERO = "/World/Hero"
CRATE = "/World/Set/PassingCrate"
BALL = "/World/Set/RollingBall"
LOOK_AT_JOINT = "pelvis"
SMOOTHING = 15.0
"""Frames: the Gaussian sigma over the pelvis path (half a second at 30 fps; the walk's sway
and the roll's tumble do not shake the camera, and it trails the roll by a few frames only)."""
# (frame, orbit angle about +Y in degrees, distance to the target, elevation in degrees).
# At 0 degrees the camera looks along -Z, at the hero's front. Distances keep the whole
# body in frame with the 30 mm lens at 16:9 (the feet are 98 cm below the pelvis, the hands
# up to 110 cm above it in the stretch and the yoga).
CAMERA_KEYS = (
    (0, -20.0, 760.0, 4.0),  # walk: wide, following the loop
    (330, 28.0, 760.0, 5.0),
    (480, 12.0, 660.0, 5.0),  # wave: in closer
    (780, -8.0, 700.0, 4.0),  # stretch, with the crouch; low, so the crate hides the legs
    (1050, -18.0, 800.0, 6.0),  # roll: out again, it travels 4.5 m in 3 s
    (1330, 10.0, 720.0, 5.0),  # yoga: distance and height held, the orbit goes on
    (1619, 40.0, 720.0, 5.0),
)
# (first frame, last frame, fraction of the way from the hero to the camera, half length of
# the path, direction +1 left to right on screen): the crate crosses in front (fraction > 0)
# and the ball rolls behind (fraction < 0), centred on the hero at the middle frame. The
# middles (200, 800; 600, 1400) are frames the README's render puts on its contact sheet.
CRATE_CROSSINGS = ((60, 340, 0.26, 700.0, 1), (680, 920, 0.22, 380.0, -1))
BALL_CROSSINGS = ((500, 700, -0.45, 480.0, -1), (1290, 1510, -0.45, 480.0, 1))


def pelvis_path(stage: Usd.Stage, frames: np.ndarray) -> np.ndarray:
    """(N, 3) world position of the hero's look-at joint at each frame."""
    from rigspace.sdk.posing import CharacterRig

    rig = CharacterRig(stage.GetPrimAtPath(HERO))
    joint = next(k for k, j in enumerate(rig.joints) if j.split("/")[-1] == LOOK_AT_JOINT)
    return np.array([rig.world_transforms(float(t))[joint, :3, 3] for t in frames])


def smooth(path: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along the first axis; the ends are held (edge padding)."""
    radius = int(3 * sigma)
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.pad(path, ((radius, radius), (0, 0)), mode="edge")
    return np.stack([np.convolve(padded[:, k], kernel, "valid") for k in range(path.shape[1])], 1)


def eased(keys: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Keyframed values (K, 1 + C) at `frames`, eased in and out of every key (cosine)."""
    k = np.clip(np.searchsorted(keys[:, 0], frames, side="right") - 1, 0, len(keys) - 2)
    u = np.clip((frames - keys[k, 0]) / (keys[k + 1, 0] - keys[k, 0]), 0.0, 1.0)
    w = (0.5 - 0.5 * np.cos(np.pi * u))[:, None]
    return keys[k, 1:] * (1 - w) + keys[k + 1, 1:] * w


def orbit(angle: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """Vectors (N, 3) rotated by angles (N,) in degrees about +Y (USD's rotateY)."""
    a = np.radians(angle)
    c, s = np.cos(a), np.sin(a)
    x, y, z = vector.T
    return np.stack([c * x + s * z, y, -s * x + c * z], 1)


def camera_rig(frames: np.ndarray, pelvis: np.ndarray) -> dict[str, np.ndarray]:
    """The camera's op values at `frames` and its world position ("eye")."""
    target = smooth(pelvis, SMOOTHING)
    angle, distance, elevation = eased(np.array(CAMERA_KEYS), frames).T
    e = np.radians(elevation)
    dolly = np.stack([np.zeros_like(e), distance * np.sin(e), distance * np.cos(e)], 1)
    eye = target + orbit(angle, dolly)
    return {"target": target, "orbit": angle, "dolly": dolly, "tilt": -elevation, "eye": eye}


def crossing_path(frames, rig, crossings, height: float) -> dict[float, np.ndarray]:
    """Translate samples of a prop crossing the camera's view: two per crossing, straight and
    at constant speed, centred on the line from the hero to the camera at mid-crossing."""
    samples: dict[float, np.ndarray] = {}
    for first, last, fraction, half, direction in crossings:
        mid = int(np.searchsorted(frames, (first + last) / 2))
        target, eye = rig["target"][mid], rig["eye"][mid]
        ground = np.array([1.0, 0.0, 1.0])
        centre = (target + fraction * (eye - target)) * ground
        back = (eye - target) * ground
        right = np.cross(np.array([0.0, 1.0, 0.0]), back / np.linalg.norm(back))
        for frame, side in ((first, -1), (last, 1)):
            point = centre + side * direction * half * right
            samples[float(frame)] = point + np.array([0.0, height, 0.0])
    return samples


def _vec(values) -> str:
    return "(" + ", ".join(f"{v:.1f}".replace("-0.0", "0.0") for v in values) + ")"


def _scalar(value: float) -> str:
    return f"{value:.2f}".replace("-0.00", "0.00")


def sample_block(samples: dict[float, str], indent: str, per_line: int) -> str:
    """The lines of a timeSamples block's body, `per_line` samples to a line."""
    items = [f"{t:g}: {v}," for t, v in sorted(samples.items())]
    lines = [" ".join(items[k : k + per_line]) for k in range(0, len(items), per_line)]
    return "".join(f"{indent}    {line}\n" for line in lines) + indent


def replace_samples(
    text: str, prim: str, attribute: str, samples: dict[float, str], per_line: int = 1
) -> str:
    """`text` with the body of `prim`'s `attribute.timeSamples = {...}` block replaced."""
    start = text.index(f'"{prim}"')
    pattern = re.compile(
        rf"(\n(\s*)[\w\[\]]+ {re.escape(attribute)}\.timeSamples = {{\n)[^}}]*(}})"
    )
    match = pattern.search(text, start)
    if match is None:
        raise SystemExit(f"{SCENE.name}: {prim} has no {attribute}.timeSamples block to fill.")
    body = sample_block(samples, match.group(2), per_line)
    return text[: match.start(1)] + match.group(1) + body + "}" + text[match.end(3) :]


def build(text: str, stage: Usd.Stage) -> str:
    """previs.usda's text with the shot's samples regenerated."""
    start, end = int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode())
    frames = np.arange(start, end + 1, dtype=np.float64)
    rig = camera_rig(frames, pelvis_path(stage, frames))
    # Baked on every frame, as a DCC bakes a constraint: each frame's camera is the rig's
    # exact look-at, and a held stretch is exactly still (USD's linear interpolation between
    # two equal vectors can differ from them in the last bit).
    ops = {
        "xformOp:translate:target": ([_vec(v) for v in rig["target"]], 5),
        "xformOp:rotateY": ([_scalar(v) for v in rig["orbit"]], 10),
        "xformOp:translate:dolly": ([_vec(v) for v in rig["dolly"]], 5),
        "xformOp:rotateX": ([_scalar(v) for v in rig["tilt"]], 10),
    }
    for attribute, (values, per_line) in ops.items():
        samples = dict(zip(frames.tolist(), values, strict=True))
        text = replace_samples(text, "ShotCam", attribute, samples, per_line)
    # On the ground: the cube's centre half its size up, the sphere's its radius.
    size = UsdGeom.Cube(stage.GetPrimAtPath(CRATE)).GetSizeAttr().Get()
    radius = UsdGeom.Sphere(stage.GetPrimAtPath(BALL)).GetRadiusAttr().Get()
    crate = crossing_path(frames, rig, CRATE_CROSSINGS, size / 2)
    ball = crossing_path(frames, rig, BALL_CROSSINGS, radius)
    text = replace_samples(
        text, "PassingCrate", "xformOp:translate", {t: _vec(p) for t, p in crate.items()}
    )
    # A quarter turn per crossing: the crate is pushed and spins as it slides.
    spin = {float(f): _scalar(90.0 * (k // 2 + k % 2)) for k, f in enumerate(sorted(crate))}
    text = replace_samples(text, "PassingCrate", "xformOp:rotateY", spin)
    return replace_samples(
        text, "RollingBall", "xformOp:translate", {t: _vec(p) for t, p in ball.items()}
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if previs.usda is stale")
    args = parser.parse_args(argv)
    import rigspace.sdk  # noqa: F401  (registers the rigspace schemas before the stage opens)

    text = SCENE.read_text()
    built = build(text, Usd.Stage.Open(str(SCENE)))
    if args.check:
        if built != text:
            print(f"{SCENE} is stale: run {Path(__file__).name} to regenerate it.")
            return 1
        print(f"{SCENE} is up to date.")
        return 0
    SCENE.write_text(built)
    print(f"wrote the shot's samples into {SCENE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

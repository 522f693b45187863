"""Builder of the film-weight sample character: the sample humanoid made heavy, as a film
character is (issue 23).

From the committed sample character (`samples/character/sample_character.usda`, its own
builder's output) it adds:

- **fingers**: five per hand, three joints each (thumb, index, middle, ring, pinky; UE names
  `index_01_l` ...): 52 joints; a `Hands` mesh of finger tubes skinned to them, with its own
  material (`Gloves`, a 2K leather texture); the fingers curl over the clips;
- **a face**: 15 UsdSkel blend shapes on the body (ARKit names: jawOpen, mouthSmileLeft/Right,
  mouthFrownLeft/Right, eyeBlinkLeft/Right, browInnerUp, browDownLeft/Right,
  cheekPuffLeft/Right, mouthPucker, noseSneerLeft/Right), jawOpen, the smiles and the blinks
  with a corrective inbetween at weight 0.5 (what the shape must look like half way, not the
  linear blend); the animation talks, blinks and smiles over the clips, and the shapes it leaves
  still (cheeks, pucker, sneer, brow down, frowns) are drawn by the capture ring within authored
  ranges; eyeballs (`Eyes`, a 1K iris texture) skinned to the head;
- **density**: the body subdivided (edge midpoints, `rigspace.sdk.geometry.subdivide_triangles`:
  skin weights, uvs, colours and every blend shape's offsets interpolated), three steps by
  default: about 1.5 million triangles at render time, displaced along the normals by a
  relief of up to 1.2 mm (cloth ribs and folds, a skin grain: `displacement`), the detail the
  extra triangles carry;
- **4K textures**: the body's albedo at 4096x4096 (the sample's painting upsampled, with a
  fabric weave and skin grain at texel scale);

and a shot (`film.usda`): the previs set, camera and lights around it, with a capture ring.
Everything is written to one folder (default `samples/film_character/build`, ignored by git:
the files are large): `film_character.usdc`, `textures/`, `film.usda`.

    python samples/film_character/build_film_character.py [--out DIR] [--subdivisions 3]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

from rigspace.sdk.geometry import dense_skin_weights, sparse_skin_weights, subdivide_triangles

HERE = Path(__file__).resolve().parent
SAMPLES = HERE.parent
BASE = SAMPLES / "character" / "sample_character.usda"
PREVIS = SAMPLES / "scenes" / "previs.usda"
MODEL = SAMPLES / "models" / "film"
"""The film character's model bundle, trained on its shot's capture (README.md here)."""
USD_NAME = "film_character.usdc"
SCENE_NAME = "film.usda"
INFLUENCES = 4

FINGERS = {  # name: (base in the hand's frame (cm: along the arm, palm normal, forward), lengths)
    "thumb": ((4.0, -0.4, 3.6), (3.4, 2.9, 2.5)),
    "index": ((15.2, 0.0, 1.65), (4.2, 2.6, 2.0)),
    "middle": ((15.6, 0.0, 0.55), (4.6, 2.9, 2.2)),
    "ring": ((15.3, 0.0, -0.55), (4.3, 2.7, 2.1)),
    "pinky": ((14.6, 0.0, -1.65), (3.4, 2.1, 1.8)),
}
THUMB_DIRECTION = np.array([0.75, -0.15, 0.65])
FINGER_RADIUS = (0.82, 0.62)
"""Finger tube radius at the knuckle and at the tip (cm)."""

# The face, in the bind pose's skeleton space (cm): the head's front is +Z.
MOUTH = np.array([0.0, 163.2, 10.0])
"""The painted lips' centre (the sample texture's), corners at x = +-2.3."""
EYE = np.array([3.8, 169.9, 8.5])
"""The left eyeball's centre, under the painted eye (the sample texture's, at z 9.3)."""
EYE_RADIUS = 1.05
JAW_PIVOT = np.array([0.0, 165.5, -1.0])


def _gauss(points: np.ndarray, centre, sigma) -> np.ndarray:
    d = (points - np.asarray(centre)) / np.asarray(sigma, dtype=float)
    return np.exp(-0.5 * np.sum(d * d, axis=1))


def _sided(points: np.ndarray, centre: np.ndarray, sigma, side: int) -> np.ndarray:
    return _gauss(points, centre * np.array([side, 1.0, 1.0]), sigma)


def _jaw(points: np.ndarray, degrees: float) -> np.ndarray:
    """Offsets that turn the lower face about the jaw's hinge (X axis through JAW_PIVOT)."""
    w = np.clip((165.0 - points[:, 1]) / 2.5, 0, 1) * np.clip((points[:, 1] - 153.0) / 3.0, 0, 1)
    w *= np.clip((points[:, 2] + 1.0) / 4.0, 0, 1) * (np.abs(points[:, 0]) < 8.5)
    a = np.radians(degrees) * w
    rel = points - JAW_PIVOT
    y = rel[:, 1] * np.cos(a) - rel[:, 2] * np.sin(a)
    z = rel[:, 1] * np.sin(a) + rel[:, 2] * np.cos(a)
    return np.stack([np.zeros_like(y), y - rel[:, 1], z - rel[:, 2]], axis=1)


def face_shapes(
    points: np.ndarray,
) -> dict[str, tuple[np.ndarray, dict[str, tuple[float, np.ndarray]]]]:
    """name -> (offsets (P, 3), {inbetween name: (weight, offsets)}) on the body's points."""
    shapes: dict[str, tuple[np.ndarray, dict]] = {}
    jaw = _jaw(points, 16.0)
    # Corrective: half way, the jaw has dropped less than half and the lips stay forward.
    shapes["jawOpen"] = (
        jaw,
        {
            "jawOpenHalf": (
                0.5,
                _jaw(points, 6.5) + [0, 0, 0.15] * (np.abs(jaw).sum(1, keepdims=True) > 0),
            )
        },
    )
    for side, tag in ((1, "Left"), (-1, "Right")):
        corner = MOUTH + np.array([2.3, 0.0, -0.4])
        w = _sided(points, corner, (1.4, 1.1, 1.6), side)[:, None]
        smile = w * np.array([0.7 * side, 1.2, -0.5])
        cheek = _sided(points, corner + np.array([1.2, 1.6, -0.8]), (1.6, 1.2, 1.6), side)[:, None]
        shapes[f"mouthSmile{tag}"] = (
            smile + 0.35 * cheek * [0, 0.6, 0.3],
            {f"mouthSmile{tag}Half": (0.5, 0.62 * smile + 0.3 * cheek * [0, 0.4, 0.25])},
        )
        shapes[f"mouthFrown{tag}"] = (w * np.array([0.2 * side, -1.1, 0.0]), {})
        lid = _sided(points, EYE + np.array([0.0, 1.0, 0.8]), (1.5, 0.8, 1.2), side)[:, None]
        shapes[f"eyeBlink{tag}"] = (
            lid * np.array([0.0, -1.3, -0.2]),
            {f"eyeBlink{tag}Half": (0.5, lid * np.array([0.0, -0.5, 0.05]))},
        )
        brow = _sided(points, EYE + np.array([0.4, 3.0, 0.2]), (1.3, 0.9, 1.5), side)[:, None]
        shapes[f"browDown{tag}"] = (brow * np.array([0.0, -0.6, 0.1]), {})
        puff = _sided(points, MOUTH + np.array([4.6, 1.0, -1.8]), (1.8, 1.6, 1.8), side)[:, None]
        outward = np.array([0.55 * side, 0.0, 0.45])
        shapes[f"cheekPuff{tag}"] = (puff * outward, {})
        sneer = _sided(points, np.array([1.2, 166.2, 9.9]), (0.9, 0.8, 1.0), side)[:, None]
        shapes[f"noseSneer{tag}"] = (sneer * np.array([0.1 * side, 0.45, -0.1]), {})
    inner = _gauss(points, (0.0, 172.2, 9.6), (2.0, 0.9, 1.5))[:, None]
    shapes["browInnerUp"] = (inner * np.array([0.0, 0.8, 0.0]), {})
    lips = _gauss(points, MOUTH, (2.2, 1.3, 1.4))[:, None]
    squeeze = lips * (MOUTH - points) * [0.25, 0.0, 0.0]
    shapes["mouthPucker"] = (lips * np.array([0.0, 0.0, 1.1]) + squeeze, {})
    order = [
        "jawOpen", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight",
        "eyeBlinkLeft", "eyeBlinkRight", "browInnerUp", "browDownLeft", "browDownRight",
        "cheekPuffLeft", "cheekPuffRight", "mouthPucker", "noseSneerLeft", "noseSneerRight",
    ]  # fmt: skip
    return {name: shapes[name] for name in order}


ANIMATED = (
    "jawOpen",
    "mouthSmileLeft",
    "mouthSmileRight",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "browInnerUp",
)
"""The shapes the clips move; the capture ring draws the others (blendShapeRanges)."""


def face_weights(t: np.ndarray) -> np.ndarray:
    """(F, len(ANIMATED)) weights over time codes `t`: talking, blinking every 3 s, smiling in
    the wave clip, brows up in the stretch clip."""
    talk = 0.5 + 0.5 * np.sin(2 * np.pi * t / 11.0) * np.sin(2 * np.pi * t / 47.0)
    jaw = np.clip(0.55 * talk * (0.6 + 0.4 * np.sin(2 * np.pi * t / 200.0)), 0, 1)
    phase = np.mod(t, 90.0)
    blink = np.clip(1.0 - np.abs(phase - 4.0) / 4.0, 0, 1)
    smile = np.clip((t - 380.0) / 40.0, 0, 1) * np.clip((590.0 - t) / 40.0, 0, 1) * 0.9
    smile += 0.15 * (0.5 + 0.5 * np.sin(2 * np.pi * t / 160.0))
    brows = np.clip((t - 620.0) / 30.0, 0, 1) * np.clip((940.0 - t) / 30.0, 0, 1) * 0.8
    return np.stack([jaw, smile, 0.9 * smile, blink, blink, brows], axis=1).astype(np.float32)


def finger_curl(t: np.ndarray) -> np.ndarray:
    """(F,) curl of every finger joint in degrees: open and closing through the clips, a fist
    in the roll clip."""
    curl = 25.0 + 20.0 * np.sin(2 * np.pi * t / 70.0)
    fist = np.clip((t - 980.0) / 30.0, 0, 1) * np.clip((1240.0 - t) / 30.0, 0, 1)
    return curl * (1 - fist) + 80.0 * fist


SIDES = {"l": np.array([1.0, 1.0, 1.0]), "r": np.array([-1.0, 1.0, 1.0])}
"""Each hand's mirror of FINGERS: the left arm's bones run along its joints' local +X, the
right arm's along -X (`hand_r` sits at x = -26 from its parent), both frames unrotated, so the
right hand's fingers are the left's with X negated."""


def finger_joints(joints: list[str]) -> list[tuple[str, int, np.ndarray]]:
    """(path, parent index, (3,) local translation) per finger joint, parents first; finger
    joints keep their hand's orientation (the arm chain's rest frame: bone along local +X on
    the left, -X on the right: SIDES)."""
    out: list[tuple[str, int, np.ndarray]] = []
    paths = list(joints)
    for tag, mirror in SIDES.items():
        hand = next(i for i, j in enumerate(paths) if j.endswith(f"/hand_{tag}"))
        for finger, (base, lengths) in FINGERS.items():
            direction = mirror * (
                THUMB_DIRECTION / np.linalg.norm(THUMB_DIRECTION)
                if finger == "thumb"
                else np.array([1.0, 0, 0])
            )
            parent, offset = hand, mirror * np.array(base, dtype=float)
            for k, length in enumerate(lengths):
                path = f"{paths[parent]}/{finger}_{k + 1:02d}_{tag}"
                out.append((path, parent, offset))
                paths.append(path)
                parent, offset = len(paths) - 1, direction * length
    return out


def _tube(a: np.ndarray, b: np.ndarray, radius: tuple[float, float], rings: int, segments: int):
    """Points (rings * segments, 3) of a tube from a to b, and (u, v) per point."""
    axis = (b - a) / np.linalg.norm(b - a)
    side = np.cross(axis, [0.0, 1.0, 0.0])
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array([0, 0, 1.0])
    up = np.cross(side, axis)
    s = np.linspace(0, 1, rings)
    angle = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    r = radius[0] + (radius[1] - radius[0]) * s
    ring = np.cos(angle)[None, :, None] * side + np.sin(angle)[None, :, None] * up
    points = a + s[:, None, None] * (b - a) + r[:, None, None] * ring
    uv = np.stack(np.meshgrid(angle / (2 * np.pi), s), axis=-1)
    return points.reshape(-1, 3), uv.reshape(-1, 2)


def _finger_chains(fingers: list[tuple[str, int, np.ndarray]]) -> list[list[str]]:
    """Each finger's joint paths, base to tip (one list per finger and side)."""
    chains: dict[str, list[str]] = {}
    for path, _, _ in fingers:
        chains.setdefault(path.rsplit("/", 1)[-1][:-5] + path[-2:], []).append(path)
    return list(chains.values())


def _finger_tube(
    chain: list[str],
    skel_points: dict[str, np.ndarray],
    index: dict[str, int],
    segments: int,
    rings_per: int,
):
    """One finger's tube along its phalanges and the tip point that caps it (last): points,
    uvs, and two influences per point (the phalanx's joint, blended with its parent's at the
    knuckle)."""
    hand = chain[0].rsplit("/", 1)[0]
    stops = [skel_points[p] for p in chain]
    tip = stops[-1] + (stops[-1] - stops[-2]) * 0.9
    stops.append(tip)
    chain_points, chain_uv, chain_idx, chain_wts = [], [], [], []
    for k in range(len(chain)):
        a, b = stops[k], stops[k + 1]
        r0 = FINGER_RADIUS[0] + (FINGER_RADIUS[1] - FINGER_RADIUS[0]) * k / len(chain)
        r1 = FINGER_RADIUS[0] + (FINGER_RADIUS[1] - FINGER_RADIUS[0]) * (k + 1) / len(chain)
        p, uv = _tube(a, b, (r0, r1), rings_per, segments)
        if k:  # the first ring is the previous phalanx's last
            p, uv = p[segments:], uv[segments:]
        chain_points.append(p)
        chain_uv.append(uv * [1.0, 1.0 / len(chain)] + [0.0, k / len(chain)])
        s = np.repeat(np.linspace(0, 1, rings_per)[1 if k else 0 :], segments)
        joint = index[chain[k]]
        parent = index[hand] if k == 0 else index[chain[k - 1]]
        blend = np.clip(0.5 - s * 2.0, 0, 0.5)  # the knuckle blends with the parent
        chain_idx.append(np.stack([np.full_like(s, joint), np.full_like(s, parent)], 1))
        chain_wts.append(np.stack([1 - blend, blend], 1))
    p = np.concatenate([np.concatenate(chain_points), tip[None]])
    uv = np.concatenate([np.concatenate(chain_uv), [[0.5, 1.0]]])
    ci = np.concatenate([np.concatenate(chain_idx), [[index[chain[-1]], index[chain[-1]]]]])
    cw = np.concatenate([np.concatenate(chain_wts), [[1.0, 0.0]]])
    return p, uv, ci, cw


def _capped_tube_triangles(start: int, cap: int, segments: int) -> list[tuple[int, int, int]]:
    """Triangles of a tube whose rings of `segments` points begin at point `start`, closed by
    a fan to its tip, point `start + cap`."""
    tris = []
    n_rings = cap // segments
    for r in range(n_rings - 1):
        for k in range(segments):
            a0, a1 = r * segments + k, r * segments + (k + 1) % segments
            b0, b1 = a0 + segments, a1 + segments
            tris += [(start + a0, start + b0, start + a1), (start + a1, start + b0, start + b1)]
    last = (n_rings - 1) * segments
    for k in range(segments):
        tris.append((start + last + k, start + cap, start + last + (k + 1) % segments))
    return tris


def hands_mesh(
    skel_points: dict[str, np.ndarray],
    fingers: list[tuple[str, int, np.ndarray]],
    joints: list[str],
):
    """Finger tubes (capped), their face-varying uvs and 4-influence skin: points, triangles,
    corner uvs, joint indices, joint weights."""
    segments, rings_per = 10, 4
    points, tris, uvs, idx, wts = [], [], [], [], []
    index = {j: i for i, j in enumerate(joints)}
    for chain in _finger_chains(fingers):
        start = sum(len(p) for p in points)
        p, uv, ci, cw = _finger_tube(chain, skel_points, index, segments, rings_per)
        tris += _capped_tube_triangles(start, len(p) - 1, segments)
        points.append(p)
        uvs.append(uv)
        idx.append(ci)
        wts.append(cw)
    points_a = np.concatenate(points)
    tris_a = np.array(tris, dtype=np.int64)
    uv_a = np.concatenate(uvs)
    pad = INFLUENCES - 2
    idx_a = np.concatenate([np.concatenate(idx), np.zeros((len(points_a), pad))], 1).astype(
        np.int32
    )
    wts_a = np.concatenate([np.concatenate(wts), np.zeros((len(points_a), pad))], 1).astype(
        np.float32
    )
    return points_a, tris_a, uv_a[tris_a.reshape(-1)], idx_a, wts_a


def sphere(centre: np.ndarray, radius: float, rings: int = 12, segments: int = 18):
    """A uv sphere's points, triangles and corner uvs (u around Y, the front (+Z) at u 0.5)."""
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    points = np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], -1)
    points = centre + radius * points.reshape(-1, 3)
    uv = np.stack([np.mod(p / (2 * np.pi) + 0.5, 1.0001), 1 - t / np.pi], -1).reshape(-1, 2)
    tris = []
    for r in range(rings):
        for k in range(segments):
            a, b = r * (segments + 1) + k, r * (segments + 1) + k + 1
            c, d = a + segments + 1, b + segments + 1
            if r:
                tris.append((a, c, b))
            if r < rings - 1:
                tris.append((b, c, d))
    tris_a = np.array(tris, dtype=np.int64)
    return points, tris_a, uv[tris_a.reshape(-1)]


def _noise(size: int, scale: int, rng: np.random.Generator) -> np.ndarray:
    small = rng.standard_normal((max(2, size // scale), max(2, size // scale))).astype(np.float32)
    return cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)


def write_textures(folder: Path, size: int, rng: np.random.Generator) -> dict[str, str]:
    """The body's albedo at `size` (the sample's painting upsampled, with a fabric weave and a
    fine grain), the gloves' leather at size/2 and the eyes' iris at size/4; returns the
    relative paths."""
    folder.mkdir(parents=True, exist_ok=True)
    base = cv2.imread(str(SAMPLES / "character" / "textures" / "albedo.png"), cv2.IMREAD_COLOR)
    body = cv2.resize(base, (size, size), interpolation=cv2.INTER_CUBIC).astype(np.float32)
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    weave = 4.0 * np.sin(x * np.pi / 3.0) * np.sin(y * np.pi / 3.0)
    grain = 3.0 * _noise(size, 2, rng) + 4.0 * _noise(size, 16, rng)
    body = np.clip(body + (weave + grain)[..., None], 0, 255).astype(np.uint8)
    cv2.imwrite(str(folder / "body_albedo.png"), body)
    half = max(16, size // 2)
    leather = np.array([28, 122, 232], np.float32)[None, None] * (
        1.0 + 0.06 * _noise(half, 4, rng)[..., None]
    )
    seam = (np.mod(np.arange(half), half // 8) < 2).astype(np.float32)
    leather *= 1.0 - 0.35 * seam[None, :, None]
    cv2.imwrite(str(folder / "gloves_albedo.png"), np.clip(leather, 0, 255).astype(np.uint8))
    quarter = max(16, size // 4)
    v, u = np.mgrid[0:quarter, 0:quarter].astype(np.float32) / quarter
    # The front of the eye (u 0.5, v 0.5): a brown iris and a black pupil on white.
    d = np.hypot((u - 0.5) * 2.0, (v - 0.5) * 1.0)
    eye = np.full((quarter, quarter, 3), (225, 230, 236), np.float32)
    eye[d < 0.16] = (40, 70, 110)
    eye[d < 0.07] = (10, 10, 10)
    cv2.imwrite(str(folder / "eyes_albedo.png"), eye.astype(np.uint8))
    return {k: f"./textures/{k}_albedo.png" for k in ("body", "gloves", "eyes")}


def _material(stage: Usd.Stage, name: str, texture: str) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, f"/Character/Looks/{name}")
    surface = UsdShade.Shader.Define(stage, f"/Character/Looks/{name}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, f"/Character/Looks/{name}/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    tex = UsdShade.Shader.Define(stage, f"/Character/Looks/{name}/Albedo")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(texture))
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result"
    )
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tex.ConnectableAPI(), "rgb"
    )
    return material


def _mesh(
    stage, path, skeleton, points, tris, corner_uv, joint_idx, joint_wts, material, colour=None
):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tris.reshape(-1).astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr("none")
    lo, hi = points.min(axis=0), points.max(axis=0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo.tolist()), Gf.Vec3f(*hi.tolist())]))
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    )
    st.Set(Vt.Vec2fArray.FromNumpy(corner_uv.astype(np.float32)))
    if colour is not None:
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
            Vt.Vec3fArray.FromNumpy(colour.astype(np.float32))
        )
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(False, INFLUENCES).Set(
        Vt.IntArray.FromNumpy(joint_idx.reshape(-1).astype(np.int32))
    )
    binding.CreateJointWeightsPrimvar(False, INFLUENCES).Set(
        Vt.FloatArray.FromNumpy(joint_wts.reshape(-1).astype(np.float32))
    )
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    return mesh


DISPLACEMENT = 0.12
"""Largest relief of the fine surface detail (cm): what the extra triangles are there for."""


def displacement(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(P, 3) offsets along the vertex normals: cloth ribs and folds on the torso and limbs,
    a fine grain on the skin above the collar; zero near the face's features (so the blend
    shapes move the surface they were made on)."""
    normals = np.zeros_like(points)
    corners = points[tris]
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    for k in range(3):
        np.add.at(normals, tris[:, k], face)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    x, y, z = points.T
    ribs = np.sin(y * 2.4) * 0.5 + 0.5 * np.sin((x + z) * 1.7 + np.sin(y * 0.35) * 3.0)
    grain = np.sin(x * 9.1 + y * 3.3) * np.sin(z * 8.7 - y * 5.2)
    cloth = y < 152.0
    height = np.where(cloth, ribs, 0.35 * grain)
    face = np.exp(-0.5 * np.sum(((points - MOUTH) / [6.0, 5.0, 4.0]) ** 2, axis=1))
    face += np.exp(-0.5 * np.sum(((np.abs(points) - np.abs(EYE)) / [3.0, 2.5, 3.0]) ** 2, axis=1))
    return (DISPLACEMENT * height * np.clip(1.0 - face, 0, 1))[:, None] * normals


def build(out: Path, subdivisions: int = 3, texture_size: int = 4096, seed: int = 0) -> dict:
    """Write the character, its textures and its shot into `out`; returns what was built."""
    start = time.monotonic()
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    textures = write_textures(out / "textures", texture_size, rng)
    base = Usd.Stage.Open(str(BASE))
    stage = Usd.Stage.CreateNew(str(out / USD_NAME))
    for key in (
        "metersPerUnit",
        "upAxis",
        "timeCodesPerSecond",
        "framesPerSecond",
        "startTimeCode",
        "endTimeCode",
    ):
        stage.SetMetadata(key, base.GetMetadata(key))
    rig = _skeleton(stage, base)
    _animation(stage, base, rig)
    looks = {
        name: _material(stage, name, textures[key])
        for name, key in (("Body", "body"), ("Gloves", "gloves"), ("Eyes", "eyes"))
    }
    names, face = _body(stage, base, rig, looks["Body"], subdivisions)
    _hands(stage, rig, looks["Gloves"], subdivisions)
    _eyes(stage, rig, looks["Eyes"])
    stage.GetRootLayer().Save()
    scene = write_scene(out, [n for n in names if n not in ANIMATED])
    triangles = {
        m: len(UsdGeom.Mesh(stage.GetPrimAtPath(f"/Character/{m}")).GetFaceVertexCountsAttr().Get())
        for m in ("Body", "Hands", "Eyes")
    }
    return {
        "usd": str(out / USD_NAME),
        "scene": str(scene),
        "joints": len(rig.joints),
        "blend_shapes": names,
        "inbetweens": sum(len(b) for _, b in face.values()),
        "triangles": triangles,
        "seconds": round(time.monotonic() - start, 1),
    }


class _Rig(NamedTuple):
    """The built skeleton: the sample's joints and the added finger joints."""

    skeleton: UsdSkel.Skeleton
    joints: list[str]
    """Every joint path, the sample's first, then the fingers'."""
    fingers: list
    """(path, parent index, offset) per added finger joint."""
    points: dict[str, np.ndarray]
    """Each joint's bind position (where the hands are built around)."""


def _skeleton(stage: Usd.Stage, base: Usd.Stage) -> _Rig:
    """The SkelRoot and its Skeleton: the sample's joints plus a chain of finger joints."""
    skeleton0 = UsdSkel.Skeleton(base.GetPrimAtPath("/Character/Skel"))
    joints = [str(j) for j in skeleton0.GetJointsAttr().Get()]
    binds = np.array(skeleton0.GetBindTransformsAttr().Get())
    rests = np.array(skeleton0.GetRestTransformsAttr().Get())
    fingers = finger_joints(joints)
    all_joints = joints + [p for p, _, _ in fingers]
    bind_all, rest_all = list(binds), list(rests)
    skel_points: dict[str, np.ndarray] = {}
    for path, parent, offset in fingers:
        local = np.eye(4)
        local[3, :3] = offset  # row-vector: translation in the last row
        rest_all.append(local)
        bind = local @ bind_all[parent]
        bind_all.append(bind)
        skel_points[path] = bind[3, :3]
    for path in joints:
        skel_points[path] = binds[joints.index(path)][3, :3]
    root = UsdSkel.Root.Define(stage, "/Character")
    stage.SetDefaultPrim(root.GetPrim())
    skeleton = UsdSkel.Skeleton.Define(stage, "/Character/Skel")
    skeleton.CreateJointsAttr(Vt.TokenArray(all_joints))
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray.FromNumpy(np.array(bind_all)))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray.FromNumpy(np.array(rest_all)))
    UsdSkel.BindingAPI.Apply(root.GetPrim())
    return _Rig(skeleton, all_joints, fingers, skel_points)


def _animation(stage: Usd.Stage, base: Usd.Stage, rig: _Rig) -> None:
    """The sample's clips, the fingers curling, the face talking."""
    anim0 = UsdSkel.Animation(base.GetPrimAtPath("/Character/Skel/Anim"))
    anim = UsdSkel.Animation.Define(stage, "/Character/Skel/Anim")
    anim.GetPrim().SetCustomData(anim0.GetPrim().GetCustomData())
    anim.CreateJointsAttr(Vt.TokenArray(rig.joints))
    anim.CreateBlendShapesAttr(Vt.TokenArray(list(ANIMATED)))
    times = anim0.GetRotationsAttr().GetTimeSamples()
    curl = finger_curl(np.array(times))
    faces = face_weights(np.array(times))
    finger_t = np.array([o for _, _, o in rig.fingers], dtype=np.float32)
    curl_sign = np.array([-SIDES[p[-1]][0] for p, _, _ in rig.fingers])
    zeros = np.zeros(len(rig.fingers))
    scales = Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * len(rig.joints))
    anim.CreateScalesAttr(scales)
    rot_attr, tr_attr, w_attr = (
        anim.CreateRotationsAttr(),
        anim.CreateTranslationsAttr(),
        anim.CreateBlendShapeWeightsAttr(),
    )
    for k, t in enumerate(times):
        q = np.array(anim0.GetRotationsAttr().Get(t))  # (J, 4) as (i, j, k, r)
        bend = np.radians(curl[k]) / 2
        # About local Z, towards the palm (-Y): clockwise seen from +Z on the left, where the
        # fingers point along +X, anticlockwise on the right (along -X).
        fq = np.stack(
            [zeros, zeros, curl_sign * np.sin(bend), np.full(len(rig.fingers), np.cos(bend))], 1
        )
        rot_attr.Set(Vt.QuatfArray.FromNumpy(np.concatenate([q, fq]).astype(np.float32)), t)
        tr = np.array(anim0.GetTranslationsAttr().Get(t))
        tr_attr.Set(Vt.Vec3fArray.FromNumpy(np.concatenate([tr, finger_t]).astype(np.float32)), t)
        w_attr.Set(Vt.FloatArray.FromNumpy(faces[k]), t)
    UsdSkel.BindingAPI.Apply(rig.skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()]
    )


def _body(
    stage: Usd.Stage, base: Usd.Stage, rig: _Rig, look, subdivisions: int
) -> tuple[list[str], dict]:
    """The body: the sample's mesh with the face's shapes, subdivided and displaced; its
    blend shapes' names and the face's shapes."""
    body0 = UsdGeom.Mesh(base.GetPrimAtPath("/Character/Body"))
    binding0 = UsdSkel.BindingAPI(body0.GetPrim())
    points = np.array(body0.GetPointsAttr().Get(), dtype=np.float64)
    tris = np.array(body0.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    st0 = UsdGeom.PrimvarsAPI(body0).GetPrimvar("st")
    corner_uv = np.array(st0.Get(), dtype=np.float64)[np.array(st0.GetIndices())]
    colour = np.array(UsdGeom.PrimvarsAPI(body0).GetPrimvar("displayColor").Get(), dtype=np.float64)
    idx0 = np.array(binding0.GetJointIndicesPrimvar().Get()).reshape(-1, INFLUENCES)
    wts0 = np.array(binding0.GetJointWeightsPrimvar().Get()).reshape(-1, INFLUENCES)
    dense = dense_skin_weights(idx0, wts0, len(rig.joints))
    face = face_shapes(points)
    vertex = {"skin": dense, "colour": colour}
    for name, (offsets, inbetweens) in face.items():
        vertex[name] = offsets
        for between, (_, values) in inbetweens.items():
            vertex[between] = values
    for _ in range(subdivisions):
        points, tris, corner_uv, vertex = subdivide_triangles(points, tris, corner_uv, vertex)
    if subdivisions:
        points = points + displacement(points, tris)
    idx, wts = sparse_skin_weights(vertex["skin"], INFLUENCES)
    body = _mesh(stage, "/Character/Body", rig.skeleton, points, tris, corner_uv, idx, wts,
                 look, vertex["colour"])  # fmt: skip
    names = [
        _blend_shape(stage, name, vertex, inbetweens) for name, (_, inbetweens) in face.items()
    ]
    body_binding = UsdSkel.BindingAPI(body.GetPrim())
    body_binding.CreateBlendShapesAttr(Vt.TokenArray(names))
    body_binding.CreateBlendShapeTargetsRel().SetTargets(
        [Sdf.Path(f"/Character/Body/{n}") for n in names]
    )
    return names, face


def _blend_shape(stage: Usd.Stage, name: str, vertex: dict, inbetweens: dict) -> str:
    """One of the body's blend shapes, on the vertices it moves, with its inbetweens."""
    offsets = vertex[name]
    moved = np.flatnonzero(np.abs(offsets).max(axis=1) > 1e-4)
    shape = UsdSkel.BlendShape.Define(stage, f"/Character/Body/{name}")
    shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(offsets[moved].astype(np.float32)))
    shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moved.astype(np.int32)))
    for between, (weight, _) in inbetweens.items():
        inbetween = shape.CreateInbetween(between)
        inbetween.SetWeight(weight)
        inbetween.SetOffsets(Vt.Vec3fArray.FromNumpy(vertex[between][moved].astype(np.float32)))
    return name


def _hands(stage: Usd.Stage, rig: _Rig, look, subdivisions: int) -> None:
    """The gloved hands around the finger joints, one subdivision less than the body."""
    hp, ht, huv, hidx, hwts = hands_mesh(rig.points, rig.fingers, rig.joints)
    vertex = {"skin": dense_skin_weights(hidx, hwts, len(rig.joints))}
    for _ in range(max(0, subdivisions - 1)):
        hp, ht, huv, vertex = subdivide_triangles(hp, ht, huv, vertex)
    hidx, hwts = sparse_skin_weights(vertex["skin"], INFLUENCES)
    _mesh(stage, "/Character/Hands", rig.skeleton, hp, ht, huv, hidx, hwts, look)


def _eyes(stage: Usd.Stage, rig: _Rig, look) -> None:
    """Two eyes bound rigidly to the head joint."""
    head = rig.joints.index(next(j for j in rig.joints if j.endswith("/head")))
    eye_parts = [sphere(EYE * [side, 1, 1], EYE_RADIUS) for side in (1, -1)]
    offset = np.cumsum([0] + [len(p) for p, _, _ in eye_parts])
    ep = np.concatenate([p for p, _, _ in eye_parts])
    et = np.concatenate([t + o for (_, t, _), o in zip(eye_parts, offset, strict=False)])
    euv = np.concatenate([uv for _, _, uv in eye_parts])
    eidx = np.zeros((len(ep), INFLUENCES), np.int32)
    eidx[:, 0] = head
    ewts = np.zeros((len(ep), INFLUENCES), np.float32)
    ewts[:, 0] = 1.0
    _mesh(stage, "/Character/Eyes", rig.skeleton, ep, et, euv, eidx, ewts, look)


def _hand(side: str) -> dict[str, tuple[str, str]]:
    """A hand region on a ring of 8 views (a third fewer samples than the face's): its joints
    and fingers at 64x64, framed at its knuckles, the square about `middle_01_{side}` (17.6 cm
    from the hand's farthest point over the clips, where the wrist is 23.8 cm from it)."""
    fingers = [
        f"{f}_0{k}_{side}" for f in ("thumb", "index", "middle", "ring", "pinky") for k in (1, 2, 3)
    ]
    joints = ", ".join(f'"{j}"' for j in [f"hand_{side}", *fingers])
    return {
        "joint": ("token", f'"middle_01_{side}"'),
        "joints": ("token[]", f"[{joints}]"),
        "size": ("float", "36"),
        "resolution": ("int", "64"),
        "viewsPerRing": ("int", "8"),
    }


REGIONS = {
    "face": {"joint": ("token", '"head"'), "resolution": ("int", "64")},
    "leftHand": _hand("l"),
    "rightHand": _hand("r"),
}
"""The shot's regions (docs/regions.md): the head with every face shape at 64x64 and the hands
(`_hand`); the body network's 128x128 is spent on the body."""


def write_scene(out: Path, drawn: list[str]) -> Path:
    """The previs shot around the film character: its set, camera, lights and capture ring,
    the ring drawing the face shapes its clips leave still, and its model (samples/models/film,
    trained on this shot's capture: README.md here)."""
    text = PREVIS.read_text()
    text = text.replace("@../character/sample_character.usda@", f"@./{USD_NAME}@")
    model = Path(os.path.relpath(MODEL, out.resolve())).as_posix()
    text = text.replace(
        "        # Trained on this scene's capture: `rigspace train /tmp/sample_ds --out samples/models/sample`\n"
        "        uniform asset rigspace:model = @../models/sample@\n",
        "        # Trained on this shot's capture (samples/film_character/README.md)\n"
        f"        uniform asset rigspace:model = @{model}@\n",
    )
    ranges = ", ".join("(0, 0.8)" for _ in drawn)
    names = ", ".join(f'"{n}"' for n in drawn)
    text = text.replace(
        "        uniform int rigspace:captureRing:heldOutViewsPerRing = 4\n",
        "        uniform int rigspace:captureRing:heldOutViewsPerRing = 4\n"
        f"        uniform token[] rigspace:captureRing:blendShapeNames = [{names}]\n"
        f"        uniform float2[] rigspace:captureRing:blendShapeRanges = [{ranges}]\n",
    )
    text = text.replace(
        '        prepend apiSchemas = ["RigspaceCaptureRingAPI", "RigspaceLiveBindingAPI:suit"]\n',
        '        prepend apiSchemas = ["RigspaceCaptureRingAPI", "RigspaceLiveBindingAPI:suit", '
        + ", ".join(f'"RigspaceRegionAPI:{name}"' for name in REGIONS)
        + "]\n",
    )
    text = text.replace(
        "        uniform int rigspace:captureRing:heldOutViewsPerRing = 4\n",
        "        uniform int rigspace:captureRing:heldOutViewsPerRing = 4\n\n"
        "        # Regions (docs/regions.md): the face and the hands at their own resolution\n"
        + "".join(
            f"        uniform {kind} rigspace:region:{name}:{attr} = {value}\n"
            for name, attrs in REGIONS.items()
            for attr, (kind, value) in attrs.items()
        ),
    )
    text = text.replace("Previs: the sample character", "Film: the film-weight sample character", 1)
    path = out / SCENE_NAME
    path.write_text(text)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--out", default=str(HERE / "build"), help="folder for the character, textures and shot"
    )
    parser.add_argument(
        "--subdivisions",
        type=int,
        default=3,
        help="midpoint steps of the body (3: about 1.5M triangles)",
    )
    parser.add_argument(
        "--texture-size", type=int, default=4096, help="the body texture's size (4096)"
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    built = build(Path(args.out), args.subdivisions, args.texture_size, args.seed)
    total = sum(built["triangles"].values())
    print(
        f"built {built['usd']} in {built['seconds']} s: {built['joints']} joints, "
        f"{total:,} triangles ({', '.join(f'{k} {v:,}' for k, v in built['triangles'].items())}), "
        f"{len(built['blend_shapes'])} blend shapes ({built['inbetweens']} corrective inbetweens); "
        f"shot {built['scene']}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A small skinned character with several materials, written on the fly with usd-core.

One cylinder mesh (a 'body' 2 units tall) skinned to a 3-joint chain that bends over time
codes 0-12, split by material-bind GeomSubsets:

- Boots (the lowest quarter): a constant diffuseColor, no texture;
- Trousers (the middle half): a UDIM texture, tiles 1001 (front half of the turn, u in
  [0, 1)) and 1002 (back half, u in [1, 2)), a different colour and stripe count in each;
- Shirt (the top quarter): a plain texture with a checker, wrapS = mirror (u runs to 2);

and a RigspaceNeuralCharacter with a capture ring around it. Everything it reads is written
beside the scene, so tests can also break it (remove a texture, change the uvs).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

import rigspace.sdk  # noqa: F401  (schemas registered before the stage is made)

SEGMENTS, RINGS, HEIGHT, RADIUS = 24, 16, 2.0, 0.3
JOINTS = ["root", "root/mid", "root/mid/top"]
BOOTS, TROUSERS = 4, 12
"""Rings of faces [0, BOOTS) are boots, [BOOTS, TROUSERS) trousers, the rest shirt."""
CHARACTER = "/World/Hero"


def _texture(path: Path, colour: tuple[int, int, int], stripes: int, size: int = 64) -> None:
    image = np.zeros((size, size, 3), np.uint8)
    image[:] = colour
    band = size // (2 * stripes)
    for k in range(0, size, 2 * band):
        image[:, k : k + band] = (240, 240, 240)  # vertical stripes (along v)
    image[: size // 8] = (20, 20, 20)  # a dark band at the top of the image
    cv2.imwrite(str(path), image[..., ::-1])


def _material(stage: Usd.Stage, name: str, file: str | None, **inputs) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, f"/World/Looks/{name}")
    surface = UsdShade.Shader.Define(stage, f"/World/Looks/{name}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    diffuse = surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    if file is None:
        diffuse.Set(Gf.Vec3f(0.25, 0.12, 0.05))
        return material
    reader = UsdShade.Shader.Define(stage, f"/World/Looks/{name}/Reader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    texture = UsdShade.Shader.Define(stage, f"/World/Looks/{name}/Texture")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(file))
    texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
    for key, value in inputs.items():
        texture.CreateInput(key, Sdf.ValueTypeNames.Token).Set(value)
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result"
    )
    diffuse.ConnectToSource(texture.ConnectableAPI(), "rgb")
    return material


def _cylinder():
    """Points, face counts and indices, faceVarying st and each face's ring."""
    angle = np.linspace(0, 2 * np.pi, SEGMENTS, endpoint=False)
    height = np.linspace(0, HEIGHT, RINGS + 1)
    points = np.array(
        [(RADIUS * np.sin(a), h, RADIUS * np.cos(a)) for h in height for a in angle], np.float32
    )
    faces, st, ring_of = [], [], []
    for r in range(RINGS):
        for k in range(SEGMENTS):
            a, b = r * SEGMENTS + k, r * SEGMENTS + (k + 1) % SEGMENTS
            faces.append((a, b, b + SEGMENTS, a + SEGMENTS))
            u0, u1 = 2 * k / SEGMENTS, 2 * (k + 1) / SEGMENTS  # two turns of u: tiles / mirror
            v0, v1 = r / RINGS, (r + 1) / RINGS
            st += [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
            ring_of.append(r)
    return points, np.array(faces), np.array(st, np.float32), np.array(ring_of)


def new_asset_stage(path: Path) -> tuple[Usd.Stage, UsdSkel.Skeleton]:
    """A new Y-up, metre stage at `path` (time codes 0-12 at 24/s, default prim /World) with
    an empty SkelRoot /World/Asset and Skeleton /World/Asset/Skel."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(12)
    stage.SetTimeCodesPerSecond(24)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    UsdSkel.Root.Define(stage, "/World/Asset")
    return stage, UsdSkel.Skeleton.Define(stage, "/World/Asset/Skel")


def add_character(
    stage: Usd.Stage,
    skeleton: UsdSkel.Skeleton,
    look_at: str,
    clip: str,
    ring: dict | None = None,
    camera_distance: float = 4.0,
) -> Usd.Prim:
    """A RigspaceNeuralCharacter at CHARACTER on `skeleton` with a small capture ring (8 views,
    32x32, one clip over time codes 0-12, 4 held-out views; `ring` adds or overrides ring
    attributes: name -> (type, value)) and a camera /World/Camera in front of it."""
    character = stage.DefinePrim(CHARACTER, "RigspaceNeuralCharacter")
    character.ApplyAPI("RigspaceCaptureRingAPI")
    character.CreateRelationship("rigspace:skeleton").SetTargets([skeleton.GetPath()])
    character.CreateAttribute("rigspace:lookAtJoint", Sdf.ValueTypeNames.Token).Set(look_at)
    attributes = {
        "viewsPerRing": (Sdf.ValueTypeNames.Int, 8),
        "elevations": (Sdf.ValueTypeNames.FloatArray, [0.0]),
        "radius": (Sdf.ValueTypeNames.Float, 5.0),
        "resolution": (Sdf.ValueTypeNames.Int, 32),
        "clipNames": (Sdf.ValueTypeNames.TokenArray, [clip]),
        "clipRanges": (Sdf.ValueTypeNames.Float2Array, [(0.0, 12.0)]),
        "heldOutViewsPerRing": (Sdf.ValueTypeNames.Int, 4),
        **(ring or {}),
    }
    for name, (kind, value) in attributes.items():
        character.CreateAttribute(f"rigspace:captureRing:{name}", kind).Set(value)
    camera = UsdGeom.Camera.Define(stage, "/World/Camera")
    camera.CreateFocalLengthAttr(35.0)
    camera.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100.0))
    UsdGeom.XformCommonAPI(camera).SetTranslate(Gf.Vec3d(0, 1.0, camera_distance))
    return character


def quad_mesh(stage: Usd.Stage, path: str, points: np.ndarray, faces: np.ndarray) -> UsdGeom.Mesh:
    """A Mesh at `path` of `points` and (F, 4) quads `faces`, not subdivided."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    mesh.CreateFaceVertexCountsAttr([4] * len(faces))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(faces.reshape(-1).tolist()))
    mesh.CreateSubdivisionSchemeAttr("none")
    return mesh


def _bending_chain(stage: Usd.Stage, skeleton: UsdSkel.Skeleton) -> None:
    """The 3-joint chain (joints 0.7 apart up y) and its animation: the root twists, the
    other two bend, over time codes 0-12."""
    skeleton.CreateJointsAttr(JOINTS)
    bind = [Gf.Matrix4d(1).SetTranslate(Gf.Vec3d(0, y, 0)) for y in (0.0, 0.7, 1.4)]
    rest = [Gf.Matrix4d(1).SetTranslate(Gf.Vec3d(0, y, 0)) for y in (0.0, 0.7, 0.7)]
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray(bind))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray(rest))
    animation = UsdSkel.Animation.Define(stage, "/World/Asset/Skel/Anim")
    animation.CreateJointsAttr(JOINTS)
    animation.CreateTranslationsAttr(Vt.Vec3fArray([(0, 0, 0), (0, 0.7, 0), (0, 0.7, 0)]))
    animation.CreateScalesAttr(Vt.Vec3hArray([(1, 1, 1)] * 3))
    rotations = animation.CreateRotationsAttr()
    for t in range(13):
        bend = Gf.Rotation(Gf.Vec3d(0, 0, 1), 4.0 * t).GetQuat()
        twist = Gf.Rotation(Gf.Vec3d(0, 1, 0), 15.0 * t).GetQuat()
        quats = [Gf.Quatf(twist), Gf.Quatf(bend), Gf.Quatf(bend)]
        rotations.Set(Vt.QuatfArray(quats), Usd.TimeCode(t))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()]
    )


def _skinned_body(stage: Usd.Stage, skeleton: UsdSkel.Skeleton) -> tuple[UsdGeom.Mesh, np.ndarray]:
    """The cylinder body with its faceVarying st, skinned to the chain; the mesh and each
    face's ring."""
    points, faces, st, ring_of = _cylinder()
    mesh = quad_mesh(stage, "/World/Asset/Body", points, faces)
    primvar = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    )
    primvar.Set(Vt.Vec2fArray.FromNumpy(st))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    height = points[:, 1]
    lower = np.clip(1.0 - np.abs(height - 0.35) / 0.7, 0, 1)
    weights = np.stack([lower, np.clip(1 - lower - (height > 1.4), 0, 1), height > 1.4], 1)
    weights = weights / weights.sum(axis=1, keepdims=True)
    binding.CreateJointIndicesPrimvar(False, 3).Set(Vt.IntArray([0, 1, 2] * len(points)))
    binding.CreateJointWeightsPrimvar(False, 3).Set(
        Vt.FloatArray(weights.astype(np.float32).reshape(-1).tolist())
    )
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    return mesh, ring_of


def _bind_materials(
    stage: Usd.Stage, mesh: UsdGeom.Mesh, ring_of: np.ndarray, textured: bool
) -> None:
    """Boots, trousers and shirt: a material each, bound to its rings' faces by a GeomSubset."""
    looks = {
        "Boots": _material(stage, "Leather", None),
        "Trousers": _material(
            stage, "Denim", "./trousers.<UDIM>.png" if textured else None, wrapS="clamp"
        ),
        "Shirt": _material(
            stage, "Cotton", "./shirt.png" if textured else None, wrapS="mirror", wrapT="repeat"
        ),
    }
    bounds = {"Boots": (0, BOOTS), "Trousers": (BOOTS, TROUSERS), "Shirt": (TROUSERS, RINGS)}
    for name, (first, last) in bounds.items():
        subset = UsdShade.MaterialBindingAPI.CreateMaterialBindSubset(
            UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()),
            name,
            Vt.IntArray(np.flatnonzero((ring_of >= first) & (ring_of < last)).tolist()),
        )
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(looks[name])


def use_model(scene: Path, bundle: Path) -> None:
    """Point the scene's character (CHARACTER) at the model `bundle`, saved in its layer."""
    stage = Usd.Stage.Open(str(scene))
    stage.GetPrimAtPath(CHARACTER).GetAttribute("rigspace:model").Set(str(bundle))
    stage.GetRootLayer().Save()


def write_material_character(folder: Path, textured: bool = True) -> Path:
    """The scene (see the module doc) in `folder`; returns its path. `textured` False gives
    every part a constant colour instead (a character with no texture at all)."""
    folder.mkdir(parents=True, exist_ok=True)
    _texture(folder / "trousers.1001.png", (40, 60, 160), 4)
    _texture(folder / "trousers.1002.png", (160, 40, 40), 2)
    _texture(folder / "shirt.png", (30, 140, 60), 3)
    path = folder / "characters.usda"
    stage, skeleton = new_asset_stage(path)
    _bending_chain(stage, skeleton)
    mesh, ring_of = _skinned_body(stage, skeleton)
    _bind_materials(stage, mesh, ring_of, textured)
    add_character(stage, skeleton, "root/mid", "bend", camera_distance=4.0)
    stage.GetRootLayer().Save()
    return path

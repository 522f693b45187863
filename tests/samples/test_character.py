"""The sample humanoid: reproducible build, closed skinned mesh, texture, clips that deform."""

from __future__ import annotations

import importlib.util
import itertools
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Usd, UsdGeom, UsdShade, UsdSkel

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "samples" / "character"
BUILDER = SAMPLE / "build_character.py"
OUTPUTS = ("sample_character.usda", "textures/albedo.png")
REBUILD = "python samples/character/build_character.py"

REQUIRED_JOINTS = [
    "pelvis",
    "pelvis/spine_01",
    "pelvis/spine_01/spine_02",
    "pelvis/spine_01/spine_02/spine_03",
    "pelvis/spine_01/spine_02/spine_03/neck_01",
    "pelvis/spine_01/spine_02/spine_03/neck_01/head",
] + [
    path
    for side in ("l", "r")
    for path in (
        f"pelvis/spine_01/spine_02/spine_03/clavicle_{side}",
        f"pelvis/spine_01/spine_02/spine_03/clavicle_{side}/upperarm_{side}",
        f"pelvis/spine_01/spine_02/spine_03/clavicle_{side}/upperarm_{side}/lowerarm_{side}",
        f"pelvis/spine_01/spine_02/spine_03/clavicle_{side}/upperarm_{side}/lowerarm_{side}"
        f"/hand_{side}",
        f"pelvis/thigh_{side}",
        f"pelvis/thigh_{side}/calf_{side}",
        f"pelvis/thigh_{side}/calf_{side}/foot_{side}",
        f"pelvis/thigh_{side}/calf_{side}/foot_{side}/ball_{side}",
    )
]
MIN_JOINTS = 20
MIN_TRIANGLES = 10_000
MIN_CLIPS = 5
MIN_FRAMES = 1500
HEIGHT_RANGE_CM = (170.0, 190.0)
FLOOR_TOLERANCE_CM = 0.5
MAX_INFLUENCES = 4
WEIGHT_SUM_TOLERANCE = 1e-5
TRANSFORM_TOLERANCE = 1e-5
NONTRIVIAL_WEIGHT = 0.05
MIN_BLENDED_FRACTION = 0.3
"""At least this share of points follows more than one joint with a non-trivial weight."""
MIN_TRIANGLE_AREA_CM2 = 1e-4
MIN_DEFORMATION_CM = 5.0
HOLD_CLIP = "yoga"
"""The clip that holds one pose for most of its length (so it has still frames)."""
STILL_TOLERANCE_CM = 1e-3
SAMPLES_PER_CLIP = 5


def load_builder():
    """The builder as a module (samples/ is not a package)."""
    spec = importlib.util.spec_from_file_location("build_character", BUILDER)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    # dataclasses look their module up in sys.modules while the class is created.
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def builds(tmp_path_factory) -> tuple[Path, Path]:
    """Two builds with the default seed: one through the CLI, one in-process, in parallel."""
    by_cli = tmp_path_factory.mktemp("cli")
    in_process = tmp_path_factory.mktemp("module")
    cli = subprocess.Popen(
        [sys.executable, str(BUILDER), "--out", str(by_cli), "--seed", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    load_builder().build(in_process, seed=0)
    output, _ = cli.communicate(timeout=120)
    assert cli.returncode == 0, output
    return in_process, by_cli


@pytest.fixture(scope="module")
def stage(builds) -> Usd.Stage:
    return Usd.Stage.Open(str(builds[0] / OUTPUTS[0]))


@pytest.fixture(scope="module")
def mesh(stage) -> UsdGeom.Mesh:
    return UsdGeom.Mesh(stage.GetPrimAtPath("/Character/Body"))


@pytest.fixture(scope="module")
def triangles(mesh) -> np.ndarray:
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    assert np.all(counts == 3), "the body must be all triangles"
    return np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)


@pytest.fixture(scope="module")
def clips(stage) -> dict[str, tuple[int, int]]:
    data = stage.GetPrimAtPath("/Character/Skel/Anim").GetCustomDataByKey("rigspace:clips")
    spans = {name: (int(a), int(b)) for name, (a, b) in data.items()}
    return dict(sorted(spans.items(), key=lambda item: item[1]))


@pytest.fixture(scope="module")
def skinning(stage, mesh):
    """skin(frame) -> (N,3) points skinned by USD's own UsdSkel."""
    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(stage.GetPrimAtPath("/Character")), Usd.PrimDefaultPredicate)
    skel_query = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Character/Skel")))
    query = cache.GetSkinningQuery(mesh.GetPrim())
    assert query, "the body is not skinned to the skeleton"

    def skin(frame: float) -> np.ndarray:
        points = mesh.GetPointsAttr().Get()
        xforms = skel_query.ComputeSkinningTransforms(frame)
        assert query.ComputeSkinnedPoints(xforms, points, frame)
        return np.asarray(points, dtype=np.float64)

    return skin


@pytest.mark.slow
def test_same_seed_gives_the_same_bytes(builds):
    first, second = builds
    for name in OUTPUTS:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name


def test_committed_sample_matches_a_fresh_build(builds):
    for name in OUTPUTS:
        committed = SAMPLE / name
        assert committed.exists(), f"{committed} is missing: run `{REBUILD}`"
        assert committed.read_bytes() == (builds[0] / name).read_bytes(), (
            f"{committed} differs from what the builder makes now: run `{REBUILD}` and commit"
        )


@pytest.mark.slow
def test_another_seed_changes_the_details(builds, tmp_path):
    load_builder().build(tmp_path, seed=1)
    for name in OUTPUTS:
        assert (tmp_path / name).read_bytes() != (builds[0] / name).read_bytes(), name


def test_stage_metadata(stage, clips):
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert stage.GetTimeCodesPerSecond() == 30
    assert stage.GetFramesPerSecond() == 30
    assert stage.GetStartTimeCode() == 0
    assert stage.GetEndTimeCode() == max(b for _, b in clips.values())
    root = stage.GetDefaultPrim()
    assert root.GetPath() == "/Character" and root.IsA(UsdSkel.Root)


def test_skeleton_joints_and_transforms(stage):
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Character/Skel"))
    joints = list(skel.GetJointsAttr().Get())
    assert len(joints) >= MIN_JOINTS
    missing = [j for j in REQUIRED_JOINTS if j not in joints]
    assert not missing, f"joints missing: {missing}"
    topology = UsdSkel.Topology(joints)
    assert topology.Validate()[0]
    rest = skel.GetRestTransformsAttr().Get()
    bind = np.asarray(skel.GetBindTransformsAttr().Get())
    # bindTransforms are skeleton-space (world) matrices, restTransforms parent-space.
    composed = np.asarray(UsdSkel.ConcatJointTransforms(topology, rest))
    assert np.abs(composed - bind).max() < TRANSFORM_TOLERANCE
    anim = UsdSkel.BindingAPI(skel.GetPrim()).GetAnimationSource()
    assert anim and anim.IsA(UsdSkel.Animation)
    assert list(UsdSkel.Animation(anim).GetJointsAttr().Get()) == joints


def test_body_is_a_standing_adult(mesh):
    points = np.asarray(mesh.GetPointsAttr().Get())
    low, high = HEIGHT_RANGE_CM
    assert low < points[:, 1].max() < high
    assert abs(points[:, 1].min()) < FLOOR_TOLERANCE_CM
    # Facing +Z: the nose is the front-most point of the head.
    head = points[points[:, 1] > 150]
    nose = head[np.argmax(head[:, 2])]
    assert abs(nose[0]) < 2.0 and 160 < nose[1] < 172


def test_body_mesh_is_watertight(mesh, triangles):
    points = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    assert len(triangles) >= MIN_TRIANGLES
    assert mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.rightHanded
    n = len(points)
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    # Every undirected edge in exactly two triangles, once in each direction: closed and
    # consistently oriented.
    undirected = np.unique(np.sort(directed, axis=1) @ [n, 1], return_counts=True)[1]
    assert np.all(undirected == 2)
    assert len(np.unique(directed @ [n, 1])) == len(directed)
    corners = points[triangles]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert 0.5 * np.linalg.norm(cross, axis=1).min() > MIN_TRIANGLE_AREA_CM2
    # Counter-clockwise seen from outside encloses a positive volume.
    assert np.sum(cross * corners[:, 0]) / 6.0 > 0
    # One closed genus-0 surface: V - E + F = 2.
    assert n - len(undirected) + len(triangles) == 2
    assert len(np.unique(triangles)) == n


def test_skin_weights(mesh):
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    assert binding.GetSkeletonRel().GetTargets() == ["/Character/Skel"]
    indices, weights = binding.GetJointIndicesPrimvar(), binding.GetJointWeightsPrimvar()
    assert indices.GetElementSize() == MAX_INFLUENCES == weights.GetElementSize()
    assert indices.GetInterpolation() == UsdGeom.Tokens.vertex
    n = len(mesh.GetPointsAttr().Get())
    w = np.asarray(weights.Get()).reshape(n, MAX_INFLUENCES)
    i = np.asarray(indices.Get()).reshape(n, MAX_INFLUENCES)
    assert i.min() >= 0 and i.max() < MIN_JOINTS + 2
    assert w.min() >= 0
    assert np.abs(w.sum(axis=1) - 1).max() < WEIGHT_SUM_TOLERANCE
    blended = np.mean(np.sum(w > NONTRIVIAL_WEIGHT, axis=1) > 1)
    assert blended > MIN_BLENDED_FRACTION, f"only {blended:.0%} of points blend joints"
    bind = binding.GetGeomBindTransformAttr().Get()
    assert np.allclose(np.asarray(bind), np.eye(4))


def test_uvs_and_texture(stage, mesh, triangles, builds):
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    values = np.asarray(st.ComputeFlattened())
    assert len(values) == triangles.size
    assert values.min() >= 0 and values.max() <= 1
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert material.GetPath() == "/Character/Looks/BodyMaterial"
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    texture = UsdShade.Shader(surface.GetInput("diffuseColor").GetConnectedSource()[0].GetPrim())
    assert texture.GetIdAttr().Get() == "UsdUVTexture"
    assert texture.GetInput("sourceColorSpace").Get() == "sRGB"
    assert texture.GetInput("wrapS").Get() == texture.GetInput("wrapT").Get() == "repeat"
    reader = UsdShade.Shader(texture.GetInput("st").GetConnectedSource()[0].GetPrim())
    assert reader.GetInput("varname").Get() == "st"
    path = Path(texture.GetInput("file").Get().resolvedPath)
    assert path == builds[0] / OUTPUTS[1]
    image = oiio.ImageInput.open(str(path))
    assert image is not None, oiio.geterror()
    spec = image.spec()
    image.close()
    assert (spec.width, spec.height, spec.nchannels) == (1024, 1024, 3)
    assert spec.format == oiio.UINT8
    assert UsdGeom.PrimvarsAPI(mesh).GetPrimvar("displayColor").HasValue()


def test_clip_table(stage, clips):
    assert len(clips) >= MIN_CLIPS
    spans = list(clips.values())
    assert sum(b - a + 1 for a, b in spans) >= MIN_FRAMES
    for (_, end), (start, _) in itertools.pairwise(spans):
        assert end < start, "clips overlap"
    assert spans[0][0] >= stage.GetStartTimeCode()
    assert spans[-1][1] <= stage.GetEndTimeCode()
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    frames = anim.GetRotationsAttr().GetTimeSamples()
    assert frames[0] <= spans[0][0] and frames[-1] >= spans[-1][1]
    assert anim.GetTranslationsAttr().GetNumTimeSamples() == len(frames)
    assert anim.GetScalesAttr().GetNumTimeSamples() == 0
    assert np.all(np.asarray(anim.GetScalesAttr().Get()) == 1)


def test_every_clip_deforms_the_body(mesh, clips, skinning):
    rest = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    for name, (first, last) in clips.items():
        frames = np.linspace(first, last, SAMPLES_PER_CLIP).round()
        posed = [skinning(f) for f in frames]
        assert all(np.isfinite(p).all() for p in posed), name
        moved = max(np.linalg.norm(p - rest, axis=1).max() for p in posed)
        assert moved > MIN_DEFORMATION_CM, f"{name} barely leaves the bind pose"
        within = np.linalg.norm(posed[1] - posed[2], axis=1).max()
        if name == HOLD_CLIP:
            # Frames 25% and 50% into the clip both lie in the held pose.
            assert within < STILL_TOLERANCE_CM, f"{name} is not held still"
        else:
            assert within > MIN_DEFORMATION_CM, f"{name} does not move between frames"


def joint_positions(stage, frame: float) -> dict[str, np.ndarray]:
    """Skeleton-space joint positions at a frame, by short joint name."""
    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(stage.GetPrimAtPath("/Character")), Usd.PrimDefaultPredicate)
    query = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Character/Skel")))
    xforms = np.asarray(query.ComputeJointSkelTransforms(frame))
    names = [j.split("/")[-1] for j in query.GetJointOrder()]
    return {name: m[3, :3] for name, m in zip(names, xforms, strict=True)}


def test_clips_do_what_their_names_say(stage, clips):
    first, last = clips["walk"]
    walk = [joint_positions(stage, f)["pelvis"] for f in np.linspace(first, last, 7)]
    assert max(np.linalg.norm((p - walk[0])[[0, 2]]) for p in walk) > 100, "walk stays put"
    stretch = [
        joint_positions(stage, f) for f in range(clips["stretch"][0], clips["stretch"][1], 15)
    ]
    assert any(j["hand_l"][1] > j["head"][1] and j["hand_r"][1] > j["head"][1] for j in stretch)
    roll = [joint_positions(stage, f) for f in range(clips["roll"][0], clips["roll"][1], 5)]
    assert any(j["head"][1] < j["pelvis"][1] for j in roll), "no cartwheel: never upside down"
    facing = np.array([j["ball_l"] + j["ball_r"] - j["foot_l"] - j["foot_r"] for j in roll])
    yaw = np.unwrap(np.arctan2(facing[:, 0], facing[:, 2]))
    assert np.ptp(yaw) > np.radians(350), "no full turn about the up axis"
    first, last = clips[HOLD_CLIP]
    held = joint_positions(stage, (first + last) / 2)
    feet = sorted([held["foot_l"][1], held["foot_r"][1]])
    assert feet[1] - feet[0] > 30, "the hold is not on one leg"

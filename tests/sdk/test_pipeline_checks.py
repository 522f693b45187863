"""One set of checks: what inspect calls an error, capture and render refuse in the same words.

Each case breaks the previs scene in one way (an overlay layer), then asks inspect which
commands the error stops, and runs capture's settings and the runtime engine on it: a
command that inspect says is stopped refuses with inspect's message, word for word; the
others run.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdShade, UsdSkel

from rigspace.capture.settings import resolve_settings
from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.sdk import validation
from rigspace.sdk.bundle import BundleError
from rigspace.sdk.cli import main
from rigspace.sdk.errors import RigspaceError, SceneError
from rigspace.sdk.geometry import read_mesh_source
from rigspace.sdk.stage import open_stage, overlay_layer
from tests.conftest import REPO

PREVIS = REPO / "samples" / "scenes" / "previs.usda"
MODEL = REPO / "samples" / "models" / "sample"
HERO = "/World/Hero"


def broken_previs(folder: Path, edit: Callable[[Usd.Stage, Path], None]) -> Path:
    """previs.usda under an overlay layer that `edit` changes (through a stage on it)."""
    path = folder / "broken.usda"
    layer = overlay_layer(path, PREVIS)
    stage = Usd.Stage.Open(layer)
    edit(stage, folder)
    assert layer.Save()
    return path


def look_at_tail(stage, _folder):
    stage.GetPrimAtPath(HERO).GetAttribute("rigspace:lookAtJoint").Set("tail")


def unknown_joints(stage, _folder):
    prim = stage.GetPrimAtPath(HERO)
    prim.CreateAttribute("rigspace:joints", Sdf.ValueTypeNames.TokenArray).Set(["pelvis", "wing"])


def nan_in_animation(stage, _folder):
    rotations = UsdSkel.Animation(stage.GetPrimAtPath(f"{HERO}/Asset/Skel/Anim")).GetRotationsAttr()
    values = np.array(rotations.Get(12.0))
    values[3, 1] = np.nan
    rotations.Set(values, 12.0)


def zero_meters_per_unit(stage, _folder):
    # What crashed the runtime (ZeroDivisionError) with a normalised SphereLight.
    stage.GetRootLayer().pseudoRoot.SetInfo("metersPerUnit", 0.0)
    UsdLux.SphereLight(stage.GetPrimAtPath("/World/Lights/Lamp")).CreateNormalizeAttr(True)


def _bundle_copy(stage, folder: Path) -> Path:
    bundle = folder / "bundle"
    shutil.copytree(MODEL, bundle, ignore=shutil.ignore_patterns("training"))
    stage.GetPrimAtPath(HERO).GetAttribute("rigspace:model").Set(Sdf.AssetPath(str(bundle)))
    return bundle


def corrupt_trunk(stage, folder):
    (_bundle_copy(stage, folder) / "trunk.onnx").write_bytes(b"\x08\x07corrupt")


def swapped_graph(stage, folder):
    # Loads fine, but is not the graph the export wrote (its size and sha256 differ).
    bundle = _bundle_copy(stage, folder)
    shutil.copyfile(bundle / "albedo_8.onnx", bundle / "albedo_16.onnx")


def ring_resolution(stage, _folder):
    stage.GetPrimAtPath(HERO).GetAttribute("rigspace:captureRing:resolution").Set(100)


CASES = {
    "look-at joint": (look_at_tail, {"LookAtJointMissing"}),
    "rigspace:joints": (unknown_joints, {"JointsMissing", "JointsDisagree"}),
    "NaN in the animation": (nan_in_animation, {"AnimationNotFinite"}),
    "metersPerUnit 0": (zero_meters_per_unit, {"BadMetersPerUnit"}),
    "corrupt trunk.onnx": (corrupt_trunk, {"BadModel"}),
    "a graph replaced": (swapped_graph, {"BadModel"}),
    "ring resolution": (ring_resolution, {"ResolutionNotPowerOfTwo"}),
}


def refusal(purpose: str, scene: Path) -> RigspaceError | None:
    """The error `purpose` stops with on `scene`, or None when it runs."""
    try:
        if purpose == "capture":
            resolve_settings(scene, HERO, warn=lambda _text: None)
        else:
            Engine(scene, EngineSettings(width=32, height=18)).close()
    except RigspaceError as exc:
        return exc
    return None


@pytest.mark.parametrize("case", CASES)
def test_inspect_capture_and_render_agree(tmp_path, capsys, case):
    edit, expected = CASES[case]
    scene = broken_previs(tmp_path, edit)
    code = main(["inspect", "--json", str(scene)])
    report = json.loads(capsys.readouterr().out)
    ours = [e for e in report["errors"] if e["validator"].startswith("rigspace:")]
    assert {e["code"] for e in ours} == expected and code == 1
    for purpose in ("capture", "render"):
        stopping = [e["message"] for e in ours if purpose in e["blocks"]]
        refused = refusal(purpose, scene)
        if not stopping:
            assert refused is None, f"{purpose} refused what inspect lets through: {refused}"
        elif len(stopping) == 1:
            assert refused is not None and str(refused) == stopping[0]
        else:
            assert refused is not None and f"{len(stopping)} problems" in str(refused)
            assert all(message in str(refused) for message in stopping)


def test_a_damaged_graph_is_a_bundle_error_naming_the_file(tmp_path):
    scene = broken_previs(tmp_path, corrupt_trunk)
    with pytest.raises(BundleError, match=r"trunk\.onnx cannot be loaded"):
        validation.require_valid(open_stage(scene), "render")


def test_an_fp32_only_bundle_is_valid(tmp_path):
    """A bundle exported with --no-int8 records its trunk's int8 graph as null: not an error."""

    def fp32_only(stage, folder):
        bundle = _bundle_copy(stage, folder)
        manifest = json.loads((bundle / "manifest.json").read_text())
        manifest["trunk"]["int8"] = {"trunk": None}
        for level in manifest["levels"]:
            level["int8"] = {}
        manifest.pop("int8_check", None)
        for name in [n for n in manifest["files"] if ".int8." in n]:
            del manifest["files"][name]
            (bundle / name).unlink()
        (bundle / "manifest.json").write_text(json.dumps(manifest, indent=2))

    stage = open_stage(broken_previs(tmp_path, fp32_only))
    ours = [f for f in validation.validate(stage) if f.validator.startswith("rigspace:")]
    assert not [f for f in ours if f.severity == "error"], [f.message for f in ours]
    validation.require_valid(stage, "render")


def test_inspect_says_which_commands_each_error_stops(tmp_path, capsys):
    scene = broken_previs(tmp_path, ring_resolution)
    assert main(["inspect", str(scene)]) == 1
    out = capsys.readouterr().out
    assert "Validation: 1 error (capture refuses 1, render refuses 0), 0 warnings" in out
    assert "[rigspace:CaptureRing.ResolutionNotPowerOfTwo]  stops capture" in out


def test_a_missing_up_axis_is_assumed_with_a_warning(tmp_path, capsys):
    scene = broken_previs(
        tmp_path, lambda stage, _: stage.GetRootLayer().pseudoRoot.ClearInfo("upAxis")
    )
    stage = open_stage(scene)
    findings = validation.validate(stage)
    (assumed,) = [f for f in findings if f.code == "UpAxisAssumed"]
    assert assumed.severity == "warning" and "assumes Y" in assumed.message
    # USD's own validator calls it an error; it is compliance only: no command refuses it.
    (usd,) = [f for f in findings if f.code == "MissingUpAxisMetadata"]
    assert usd.severity == "error" and usd.blocks == ()
    validation.require_valid(stage, "render")  # runs: a warning, not a refusal
    validation.require_valid(stage, "render")  # and says it once per stage
    err = capsys.readouterr().err
    assert err.count("rigspace render: warning: Stage") == 1 and "does not author upAxis" in err


def test_require_valid_checks_what_capture_reads_only(tmp_path):
    # A prop's broken texture stops render (it draws the prop), not the character's capture.
    def prop_with_missing_texture(stage, _folder):
        mesh = UsdGeom.Mesh.Define(stage, "/World/Set/Poster")
        mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
        mesh.CreateFaceVertexCountsAttr([3])
        mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
        bind_texture(stage, mesh.GetPrim(), "./missing.png")

    stage = open_stage(broken_previs(tmp_path, prop_with_missing_texture))
    validation.require_valid(stage, "capture", [stage.GetPrimAtPath(HERO)])
    with pytest.raises(SceneError, match="Poster") as refused:
        validation.require_valid(stage, "render")
    assert "/World/Set/PosterLook" in str(refused.value)


def bind_texture(stage: Usd.Stage, prim: Usd.Prim, file: str) -> None:
    """A UsdPreviewSurface material reading its diffuseColor from `file`, bound to `prim`."""
    look = f"{prim.GetPath()}Look"
    material = UsdShade.Material.Define(stage, look)
    surface = UsdShade.Shader.Define(stage, f"{look}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    texture = UsdShade.Shader.Define(stage, f"{look}/Texture")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    rgb = texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(rgb)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


def test_a_missing_texture_names_its_material_and_prim(tmp_path):
    layer = tmp_path / "textured.usda"
    stage = Usd.Stage.CreateNew(str(layer))
    UsdGeom.SetStageUpAxis(stage, "Y")
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    mesh = UsdGeom.Mesh.Define(stage, "/Box")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    bind_texture(stage, mesh.GetPrim(), "./textures/nowhere.png")
    stage.Save()
    with pytest.raises(SceneError) as refused:
        read_mesh_source(mesh.GetPrim())
    for name in ("nowhere.png", "material /BoxLook", "/BoxLook/Texture", "bound to /Box"):
        assert name in str(refused.value)
    (finding,) = [
        f for f in validation.validate(stage, include_usd=False) if f.code == "TextureMissing"
    ]
    assert finding.prim == "/Box" and "material /BoxLook" in finding.message
    assert finding.blocks == ("capture", "render")

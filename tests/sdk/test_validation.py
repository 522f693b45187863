"""Each rigspace validator: one fixture that triggers it, and the valid scene that does not."""

from __future__ import annotations

from pathlib import Path

import pytest

from rigspace.sdk import validation
from rigspace.sdk.stage import open_stage
from tests.conftest import TINY_JOINTS, write_bundle_manifest


def findings(path: Path, severity: str = validation.ERROR) -> list[validation.Finding]:
    """rigspace's findings of one severity (USD's validators run too; see the test below)."""
    return [
        f
        for f in validation.validate(open_stage(path))
        if f.severity == severity and f.validator.startswith("rigspace:")
    ]


def codes(path: Path, severity: str = validation.ERROR) -> set[str]:
    return {f.code for f in findings(path, severity) if f.validator.startswith("rigspace:")}


def test_valid_scene_has_no_errors(tiny_scene):
    path = tiny_scene()
    assert findings(path) == []
    # No model yet is a warning, not an error: the character can still be captured.
    assert codes(path, validation.WARNING) == {"NoModel"}


def test_usd_builtin_validators_run_in_the_same_context(tmp_path, tiny_scene):
    path = tiny_scene()
    path.write_text(path.read_text().replace('    upAxis = "Y"\n', ""))
    found = validation.validate(open_stage(path))
    assert any(f.validator.startswith("usdGeomValidators:") for f in found), found


@pytest.mark.parametrize(
    ("character", "body", "code"),
    [
        ("", "", None),
        ("        rel rigspace:skeleton = [ ]", "", "NoSkeleton"),
        (
            "",
            '    def Mesh "NotSkel" {}\n',
            None,
        ),
        ("        rel rigspace:skeleton = </World/Nowhere>", "", "SkeletonMissing"),
        ("        rel rigspace:skeleton = </World/Asset>", "", "NotASkeleton"),
        ("        rel rigspace:animationSource = </World/Asset>", "", "NotAnAnimation"),
        ('        uniform token rigspace:lookAtJoint = "tail"', "", "LookAtJointMissing"),
        ('        uniform token[] rigspace:joints = ["head", "wing"]', "", "JointsMissing"),
        ('        uniform token[] rigspace:maps = ["albedo", "specular"]', "", "UnknownMaps"),
    ],
)
def test_character_skeleton_rule(tiny_scene, character, body, code):
    # Later lines of a prim win in usda, so the override relationship replaces the first.
    path = tiny_scene(character=character, body=body)
    if character.startswith("        rel rigspace:skeleton"):
        text = path.read_text().replace(
            "        rel rigspace:skeleton = </World/Asset/Skel>\n", "", 1
        )
        path.write_text(text)
    got = codes(path)
    assert got == ({code} if code else set()), findings(path)
    if code:
        (finding,) = [f for f in findings(path) if f.code == code]
        assert finding.prim == "/World/Hero"
        assert "Fix:" in finding.message and "/World/Hero" in finding.message


def test_character_without_any_animation_is_an_error(tiny_scene):
    # Capture and render cannot pose it (CharacterRig refuses), so inspect says error too.
    path = tiny_scene()
    path.write_text(
        path.read_text().replace("rel skel:animationSource = </World/Asset/Skel/Anim>", "")
    )
    (finding,) = findings(path)
    assert finding.code == "NoAnimation" and finding.blocks == ("capture", "render")
    assert "has no animation" in finding.message


def test_model_that_does_not_resolve(tiny_scene):
    path = tiny_scene(character="        uniform asset rigspace:model = @./models/missing@")
    (finding,) = findings(path)
    assert finding.code == "ModelNotFound"
    # USD's own MissingReferenceValidator agrees.
    usd = {(f.validator, f.code) for f in validation.validate(open_stage(path))}
    assert ("usdUtilsValidators:MissingReferenceValidator", "UnresolvableDependency") in usd
    assert "@./models/missing@" in finding.message and "Fix:" in finding.message


def test_model_that_resolves_and_fits(tmp_path, tiny_scene):
    write_bundle_manifest(tmp_path / "model", TINY_JOINTS)
    path = tiny_scene(character="        uniform asset rigspace:model = @./model@")
    assert findings(path) == []
    assert "NoModel" not in codes(path, validation.WARNING)


def test_model_needs_joints_the_skeleton_lacks(tmp_path, tiny_scene):
    write_bundle_manifest(tmp_path / "model", [*TINY_JOINTS, "hips/spine/head/jaw", "tail"])
    path = tiny_scene(character="        uniform asset rigspace:model = @./model/manifest.json@")
    (finding,) = findings(path)
    assert finding.code == "ModelJointsMissing"
    assert "hips/spine/head/jaw" in finding.message and "tail" in finding.message


@pytest.mark.parametrize(
    ("manifest", "code"),
    [
        ("{not json", "BadModel"),
        ('{"format": "something.else"}', "BadModel"),
        ('{"format": "rigspace.bundle", "format_version": 99, "joints": ["hips"]}', "BadModel"),
    ],
)
def test_corrupt_manifest(tmp_path, tiny_scene, manifest, code):
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "manifest.json").write_text(manifest)
    path = tiny_scene(character="        uniform asset rigspace:model = @./model@")
    assert codes(path) == {code}


def test_encoding_and_joint_list_must_match_the_manifest(tmp_path, tiny_scene):
    write_bundle_manifest(tmp_path / "model", TINY_JOINTS, rotation_encoding="quaternion")
    path = tiny_scene(
        character="        uniform asset rigspace:model = @./model@\n"
        '        uniform token[] rigspace:joints = ["hips"]'
    )
    assert codes(path) == {"EncodingDisagrees", "JointsDisagree"}


@pytest.mark.parametrize(
    ("line", "code"),
    [
        ("uniform int rigspace:captureRing:viewsPerRing = 0", "ViewsOutOfRange"),
        ("uniform int rigspace:captureRing:viewsPerRing = 12", None),
        ("uniform float[] rigspace:captureRing:elevations = [0, 95]", "ElevationOutOfRange"),
        ("uniform float[] rigspace:captureRing:elevations = []", "ElevationOutOfRange"),
        ("uniform float[] rigspace:captureRing:heldOutElevations = [-90]", "ElevationOutOfRange"),
        ("uniform float rigspace:captureRing:radius = -1", "RadiusOutOfRange"),
        ("uniform float rigspace:captureRing:focalLength = 0", "LensOutOfRange"),
        ("uniform int rigspace:captureRing:resolution = 100", "ResolutionNotPowerOfTwo"),
        ("uniform int rigspace:captureRing:resolution = 8192", "ResolutionNotPowerOfTwo"),
        ("uniform int rigspace:captureRing:resolution = 256", None),
        ("uniform float2 rigspace:captureRing:clippingRange = (5, 1)", "ClippingOutOfRange"),
        ("uniform int rigspace:captureRing:heldOutViewsPerRing = 13", "HeldOutViewsOutOfRange"),
        ('uniform token rigspace:captureRing:lookAtJoint = "tail"', "LookAtJointMissing"),
        ('uniform token rigspace:captureRing:lookAtJoint = "spine"', None),
    ],
)
def test_capture_ring_ranges(tiny_scene, line, code):
    path = tiny_scene(character="        " + line)
    assert codes(path) == ({code} if code else set())


@pytest.mark.parametrize(
    ("names", "ranges", "held_out", "code"),
    [
        ('["a"]', "[(0, 4), (5, 10)]", '["a"]', "ClipsDisagree"),
        ('["a", "a"]', "[(0, 4), (5, 10)]", '["a"]', "DuplicateClips"),
        ('["a", "b"]', "[(0, 4), (5, 10)]", '["c"]', "UnknownHeldOutClips"),
        ('["a", "b"]', "[(4, 0), (5, 10)]", '["b"]', "ClipRangeBackwards"),
        ('["a", "b"]', "[(0, 4), (20, 30)]", '["b"]', "ClipOutsideAnimation"),
        # Reaching past the animation (0-10): capture clamps it, so a warning only.
        ('["a", "b"]', "[(0, 4), (5, 30)]", '["b"]', "ClipClamped"),
        # An end that rounds into the animated range (exporter drift) is the same frame.
        ('["a", "b"]', "[(0, 4), (5, 10.000001)]", '["b"]', None),
    ],
)
def test_capture_ring_clips(tiny_scene, names, ranges, held_out, code):
    path = tiny_scene()
    text = path.read_text()
    text = text.replace('clipNames = ["a", "b"]', f"clipNames = {names}")
    text = text.replace("clipRanges = [(0, 4), (5, 10)]", f"clipRanges = {ranges}")
    text = text.replace('heldOutClips = ["b"]', f"heldOutClips = {held_out}")
    path.write_text(text)
    found = codes(path) | codes(path, validation.WARNING)
    assert found - {"NoModel"} == ({code} if code else set())


def test_capture_ring_on_a_prim_that_is_not_a_character(tiny_scene):
    path = tiny_scene(
        body='    def Xform "Prop" (prepend apiSchemas = ["RigspaceCaptureRingAPI"]) {}\n'
    )
    (finding,) = findings(path)
    assert (finding.code, finding.prim) == ("NotOnCharacter", "/World/Prop")


LIVE = '"RigspaceLiveBindingAPI:suit"'


@pytest.mark.parametrize(
    ("lines", "code"),
    [
        ('uniform string rigspace:live:suit:url = "vmc://127.0.0.1:39539"', None),
        ('uniform string rigspace:live:suit:url = "serial:///dev/ttyUSB0?baudrate=115200"', None),
        ('uniform string rigspace:live:suit:url = ""', "BadUrl"),
        ('uniform string rigspace:live:suit:url = "not a url"', "BadUrl"),
        ('uniform string rigspace:live:suit:url = "vmc://127.0.0.1:99999"', "BadUrl"),
        ('uniform string rigspace:live:suit:url = "v m c://host"', "BadUrl"),
    ],
)
def test_live_binding_url(tiny_scene, lines, code):
    path = tiny_scene(character="        " + lines, extra_apis=LIVE)
    got = codes(path)
    assert got == ({code} if code else set())
    if code:
        (finding,) = findings(path)
        assert "rigspace:live:suit:url" in finding.message and "Fix:" in finding.message


@pytest.mark.parametrize(
    ("lines", "code"),
    [
        (
            [
                'uniform token[] rigspace:live:suit:sourceBones = ["Hips", "Spine"]',
                'uniform token[] rigspace:live:suit:targetJoints = ["hips"]',
            ],
            "BoneMapDisagrees",
        ),
        (
            ['uniform token[] rigspace:live:suit:targetJoints = ["hips", "tail"]'],
            "TargetJointsMissing",
        ),
        (
            [
                'uniform token[] rigspace:live:suit:targetJoints = ["hips"]',
                "uniform quatf[] rigspace:live:suit:restPose = [(2, 0, 0, 0)]",
            ],
            "RestPoseNotUnit",
        ),
        (
            [
                'uniform token[] rigspace:live:suit:targetJoints = ["hips"]',
                "uniform quatf[] rigspace:live:suit:restPose = [(1, 0, 0, 0), (1, 0, 0, 0)]",
            ],
            "RestPoseDisagrees",
        ),
        (["uniform float rigspace:live:suit:smoothingStrength = 1"], "ValueOutOfRange"),
        (["uniform float rigspace:live:suit:timeoutSeconds = 0"], "ValueOutOfRange"),
        (
            [
                'uniform token[] rigspace:live:suit:sourceBones = ["Hips"]',
                'uniform token[] rigspace:live:suit:targetJoints = ["hips"]',
                "uniform quatf[] rigspace:live:suit:restPose = [(1, 0, 0, 0)]",
            ],
            None,
        ),
    ],
)
def test_live_binding_bone_map(tiny_scene, lines, code):
    url = 'uniform string rigspace:live:suit:url = "vmc://127.0.0.1:39539"'
    body = "\n".join("        " + line for line in [url, *lines])
    path = tiny_scene(character=body, extra_apis=LIVE)
    assert codes(path) == ({code} if code else set())


def test_a_broken_validator_plugin_is_reported_not_fatal(monkeypatch, tiny_scene):
    def broken_loader():
        raise ImportError("No module named 'studio_checks'")

    real_discover = validation.discover
    monkeypatch.setattr(
        validation,
        "discover",
        lambda kind: real_discover(kind, extra={"studio": broken_loader}),
    )
    found = validation.validate(open_stage(tiny_scene()))
    (plugin,) = [f for f in found if f.code == "PluginFailed"]
    assert "studio" in plugin.message and "studio_checks" in plugin.message
    assert plugin.severity == validation.WARNING


def test_a_rule_that_raises_is_not_swallowed(monkeypatch, tiny_scene):
    def explode(prim):
        raise ZeroDivisionError("bug in a rule")
        yield  # pragma: no cover

    spec = validation.ValidatorSpec("Exploding", "always fails", explode)
    real_discover = validation.discover
    monkeypatch.setattr(
        validation, "discover", lambda kind: real_discover(kind, extra={"exploding": lambda: spec})
    )
    with pytest.raises(ZeroDivisionError, match="bug in a rule"):
        validation.validate(open_stage(tiny_scene()))

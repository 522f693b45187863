"""The codeless schema plugin: registration, fallbacks, API application, generated files in sync."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
from pxr import Sdf, Usd

import rigspace.usd_schemas as schemas
from rigspace.usd_schemas import generate


def run_python(code: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        check=False,
    )


def test_types_are_registered():
    registry = Usd.SchemaRegistry()
    assert registry.FindConcretePrimDefinition(schemas.NEURAL_CHARACTER) is not None
    assert registry.FindAppliedAPIPrimDefinition(schemas.CAPTURE_RING_API) is not None
    assert registry.FindAppliedAPIPrimDefinition(schemas.LIVE_BINDING_API) is not None
    assert Usd.SchemaRegistry.IsMultipleApplyAPISchema(schemas.LIVE_BINDING_API)
    assert not Usd.SchemaRegistry.IsMultipleApplyAPISchema(schemas.CAPTURE_RING_API)


def test_neural_character_is_xformable_with_fallbacks():
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/Hero", schemas.NEURAL_CHARACTER)
    from pxr import UsdGeom

    assert prim.IsA(UsdGeom.Xformable)
    assert prim.GetAttribute("rigspace:rotationEncoding").Get() == "rot6d"
    assert list(prim.GetAttribute("rigspace:maps").Get()) == ["albedo", "normal", "depth", "mask"]
    assert prim.GetAttribute("rigspace:trainingCamera:horizontalAperture").Get() == pytest.approx(
        20.955
    )
    assert prim.GetRelationship("rigspace:skeleton")
    # Fallbacks are not authored opinions.
    assert not prim.GetAttribute("rigspace:rotationEncoding").HasAuthoredValue()


def test_capture_ring_apply_and_fallbacks():
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/Hero", schemas.NEURAL_CHARACTER)
    assert prim.CanApplyAPI(schemas.CAPTURE_RING_API)
    assert prim.ApplyAPI(schemas.CAPTURE_RING_API)
    assert prim.HasAPI(schemas.CAPTURE_RING_API)
    assert prim.GetAttribute("rigspace:captureRing:viewsPerRing").Get() == 12
    assert prim.GetAttribute("rigspace:captureRing:resolution").Get() == 128
    assert tuple(prim.GetAttribute("rigspace:captureRing:clippingRange").Get()) == pytest.approx(
        (0.1, 10000)
    )


def test_live_binding_is_multiple_apply():
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/Hero", schemas.NEURAL_CHARACTER)
    assert prim.ApplyAPI(schemas.LIVE_BINDING_API, "suit")
    assert prim.ApplyAPI(schemas.LIVE_BINDING_API, "gamepad")
    assert prim.GetAppliedSchemas() == [
        f"{schemas.LIVE_BINDING_API}:suit",
        f"{schemas.LIVE_BINDING_API}:gamepad",
    ]
    url = prim.GetAttribute("rigspace:live:suit:url")
    assert url and url.Get() == ""
    url.Set("vmc://127.0.0.1:39539")
    assert prim.GetAttribute("rigspace:live:gamepad:url").Get() == ""
    assert prim.GetAttribute("rigspace:live:gamepad:smoothing").Get() == "none"
    assert prim.GetAttribute("rigspace:live:suit:timeoutSeconds").Get() == pytest.approx(0.5)


def test_every_property_is_namespaced_uniform_and_documented():
    layer = Sdf.Layer.FindOrOpen(os.path.join(schemas.plugin_path(), "schema.usda"))
    checked = 0
    for name in ("RigspaceNeuralCharacter", "RigspaceCaptureRingAPI", "RigspaceLiveBindingAPI"):
        spec = layer.GetPrimAtPath(f"/{name}")
        for prop in spec.properties:
            checked += 1
            if name != "RigspaceLiveBindingAPI":  # multiple-apply: prefix comes from the API
                assert prop.name.startswith("rigspace:"), prop.name
            assert len(prop.documentation) > 20, f"{name}.{prop.name} needs a doc"
            if isinstance(prop, Sdf.AttributeSpec):
                assert prop.variability == Sdf.VariabilityUniform, f"{name}.{prop.name}"
    assert checked >= 30


def test_enums_declare_allowed_tokens():
    definition = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(schemas.LIVE_BINDING_API)
    for prop in ("smoothing", "buffering", "sourceUpAxis", "sourceHandedness", "bonePreset"):
        spec = definition.GetSchemaAttributeSpec(f"rigspace:live:__INSTANCE_NAME__:{prop}")
        assert spec is not None and list(spec.allowedTokens), prop


def test_live_binding_says_what_issue_11_says():
    """Buffering is latest/delayed, a bone preset and the stale/lost thresholds are attributes,
    the gamepad map lives on the binding, and each doc starts with its unit or range."""
    layer = Sdf.Layer.FindOrOpen(os.path.join(schemas.plugin_path(), "schema.usda"))
    properties = layer.GetPrimAtPath("/RigspaceLiveBindingAPI").properties

    def spec(prop):
        return properties[prop]

    assert list(spec("buffering").allowedTokens) == ["latest", "delayed"]
    assert list(spec("bonePreset").allowedTokens) == [
        "auto", "none", "unityHumanoid", "cmu", "mixamo"
    ]  # fmt: skip
    assert spec("bonePreset").default == "auto" and spec("lostSeconds").default == 0
    assert spec("gamepadOffsets").typeName == Sdf.ValueTypeNames.StringArray
    assert spec("gamepadClips").typeName == Sdf.ValueTypeNames.StringArray
    assert "stale" in spec("timeoutSeconds").documentation
    assert "lost" in spec("lostSeconds").documentation
    for prop, unit in (
        ("bufferSeconds", "in seconds"), ("timeoutSeconds", "Seconds"), ("lostSeconds", "Seconds"),
        ("smoothingStrength", "[0, 1)"), ("sourceMetersPerUnit", "meters"),
        ("restPose", "(w, x, y, z)"), ("enabled", "true or false"),
    ):  # fmt: skip
        first = spec(prop).documentation.split(". ")[0]
        assert unit in first, (prop, first)


def test_plugin_path_needs_no_pxr():
    result = run_python(
        """
        import sys
        import rigspace.usd_schemas as s
        print(s.plugin_path())
        assert not any(m == "pxr" or m.startswith("pxr.") for m in sys.modules), "pxr imported"
        """
    )
    assert result.returncode == 0, result.stderr
    assert os.path.isfile(os.path.join(result.stdout.strip(), "plugInfo.json"))


def test_registering_too_late_raises_a_clear_error():
    result = run_python(
        """
        from pxr import Usd
        Usd.SchemaRegistry()  # builds the registry without our types
        import rigspace.sdk
        """,
        env={"PXR_PLUGINPATH_NAME": ""},
    )
    assert result.returncode != 0
    assert "SchemaRegistrationError" in result.stderr
    assert "import rigspace" in result.stderr and "PXR_PLUGINPATH_NAME" in result.stderr


def test_host_apps_register_through_the_plugin_path():
    result = run_python(
        """
        from pxr import Usd
        assert Usd.SchemaRegistry().FindConcretePrimDefinition("RigspaceNeuralCharacter")
        import rigspace.sdk  # already known through PXR_PLUGINPATH_NAME: fine, idempotent
        rigspace.sdk.ensure_registered()
        print("ok")
        """,
        env={"PXR_PLUGINPATH_NAME": schemas.plugin_path()},
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"


def test_generated_files_are_in_sync():
    pytest.importorskip("jinja2", reason="schema generation needs jinja2 (the dev extra)")
    assert generate.out_of_sync() == [], (
        "usd_schemas/schema.usda changed: run python -m rigspace.usd_schemas.generate"
    )


def test_plug_info_has_no_build_placeholders():
    text = open(os.path.join(schemas.plugin_path(), "plugInfo.json")).read()
    assert "@PLUG_INFO" not in text

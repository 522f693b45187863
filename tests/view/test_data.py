"""The data endpoints on real stages: tree, properties, composition, findings, reload."""

from __future__ import annotations

import os
import shutil

from rigspace.runtime.view.scene import SceneModel
from tests.view.conftest import BROKEN, PREVIS


def test_summary_has_the_stage_timing_cameras_and_layers(previs_client):
    s = previs_client.get("/api/summary").json()
    assert (s["start"], s["end"], s["fps"]) == (0.0, 1619.0, 30.0)
    assert s["cameras"] == ["/World/ShotCam"]
    assert [layer["name"] for layer in s["layers"]] == ["previs.usda"]
    assert any(u.endswith("sample_character.usda") for u in s["used"])
    assert s["maps"] == ["beauty", "albedo", "normal", "depth", "mask", "chart", "uv"]


def test_tree_marks_rigspace_prims_applied_schemas_and_inactive_ones(previs_client):
    rows = {r["path"]: r for r in previs_client.get("/api/tree").json()}
    hero = rows["/World/Hero"]
    assert hero["type"] == "RigspaceNeuralCharacter" and hero["rigspace"] and hero["children"]
    assert "RigspaceLiveBindingAPI:suit" in hero["applied"]
    assert not rows["/World/Set/Ground"]["rigspace"]
    assert rows["/World/Hero/Asset"]["depth"] == 2
    assert all(r["active"] for r in rows.values())  # previs deactivates nothing


def test_tree_lists_inactive_prims(tmp_path):
    # live.usda deactivates the passing crate over previs: the tree still shows it, inactive.
    model = SceneModel(PREVIS.parent / "live.usda")
    rows = {r["path"]: r for r in model.tree()}
    assert rows["/World/Set/PassingCrate"]["active"] is False


def test_properties_at_a_time_authored_fallback_samples_and_targets(previs_client):
    hero = previs_client.get("/api/prim", params={"path": "/World/Hero", "time": 10}).json()
    props = {p["name"]: p for p in hero["properties"]}
    assert props["rigspace:captureRing:clipNames"]["source"] == "authored"
    assert props["rigspace:captureRing:clipNames"]["value"][0] == "walk"
    assert props["purpose"]["source"] == "fallback"
    assert props["rigspace:skeleton"]["kind"] == "relationship"
    assert props["rigspace:skeleton"]["targets"] == ["/World/Hero/Asset/Skel"]
    assert hero["metadata"]["specifier"] == "def"
    assert "RigspaceCaptureRingAPI" in hero["metadata"]["apiSchemas"]
    bundle = hero["bundle"]
    assert bundle["manifest"].endswith("manifest.json") and bundle["levels"][-1] == 128
    assert bundle["blend_shapes"] == [] and bundle["controls"] == []  # the sample has none
    model_rows = [r for r in bundle["metrics"] if r["predictor"] == "model"]
    assert model_rows and all(r["albedo_psnr"] > 15 for r in model_rows)
    anim = previs_client.get(
        "/api/prim", params={"path": "/World/Hero/Asset/Skel/Anim", "time": 0}
    ).json()
    rotations = {p["name"]: p for p in anim["properties"]}["rotations"]
    assert rotations["samples"] > 100 and rotations["source"] == "time samples"


def test_property_values_follow_the_time(previs_client):
    def ball(t):
        rows = previs_client.get(
            "/api/prim", params={"path": "/World/Set/RollingBall", "time": t}
        ).json()["properties"]
        return {p["name"]: p for p in rows}

    early, late = ball(500), ball(600)
    sampled = [n for n, p in early.items() if p.get("samples", 0) > 0]
    assert sampled, "the rolling ball is animated by time samples"
    assert any(early[n]["value"] != late[n]["value"] for n in sampled)


def test_composition_names_the_layer_of_each_opinion(previs_client):
    c = previs_client.get("/api/composition", params={"path": "/World/Hero/Asset"}).json()
    arcs = {a["arc"] for a in c["arcs"]}
    assert "Root" in arcs and "Reference" in arcs
    layers = {a["layer"].rsplit("/", 1)[-1] for a in c["arcs"] if a["layer"]}
    assert {"previs.usda", "sample_character.usda"} <= layers
    assert c["primStack"][0]["layer"].endswith("previs.usda")


def test_findings_of_the_broken_fixture_name_their_prims(broken_client):
    found = broken_client.get("/api/findings").json()
    codes = {(f["code"], f["prim"]) for f in found}
    assert ("NotASkeleton", "/World/Hero") in codes
    assert ("ModelNotFound", "/World/Hero") in codes
    assert all(f["severity"] in ("error", "warning") for f in found)


def test_previs_has_no_findings_with_errors(previs_client):
    assert not [f for f in previs_client.get("/api/findings").json() if f["severity"] == "error"]


def test_reload_picks_up_an_edit_and_keeps_the_last_good_stage_on_a_syntax_error(tmp_path):
    scene = tmp_path / "scene.usda"
    shutil.copy(BROKEN, scene)
    model = SceneModel(scene)
    assert not model.poll()  # nothing changed
    text = scene.read_text()
    scene.write_text(text.replace('def Camera "Camera"', 'def Camera "Cam2"'))
    os.utime(scene, ns=(1, 1))  # a distinct mtime whatever the file system's resolution
    assert model.poll() and model.version == 1
    assert model.prim("/World/Cam2") is not None and model.prim("/World/Camera") is None
    scene.write_text(text + '\ndef Xform "Oops" {{{\n')
    os.utime(scene, ns=(2, 2))
    assert model.poll()
    errors = [f for f in model.findings() if f["code"] == "LayerParseError"]
    assert len(errors) == 1 and "scene.usda" in errors[0]["message"]
    assert model.prim("/World/Cam2") is not None  # the last good content stays
    scene.write_text(text)
    os.utime(scene, ns=(3, 3))
    assert model.poll()
    assert not [f for f in model.findings() if f["code"] == "LayerParseError"]
    assert model.prim("/World/Camera") is not None

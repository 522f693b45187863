"""`rigspace inspect` on the sample scenes, CesiumMan (.usdz), .usdc, and broken scenes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from pxr import Sdf

from rigspace.sdk.cli import main
from tests.conftest import CESIUM_MAN, REPO

SCENES = sorted((REPO / "samples" / "scenes").glob("*.usda"))


def inspect_json(path: Path, capsys) -> tuple[int, dict]:
    code = main(["inspect", "--json", str(path)])
    return code, json.loads(capsys.readouterr().out)


def test_sample_scenes_exist():
    names = {p.name for p in SCENES}
    assert {"previs.usda", "cesium_man.usda"} <= names


@pytest.mark.parametrize("scene", SCENES, ids=[p.stem for p in SCENES])
def test_sample_scenes_inspect_cleanly(scene, capsys):
    code, report = inspect_json(scene, capsys)
    assert set(report) == {"stage", "prims", "errors", "warnings"}
    assert report["errors"] == [] and code == 0
    kinds = {p["kind"] for p in report["prims"]}
    assert {
        "neuralCharacter",
        "skeleton",
        "skelAnimation",
        "skinnedMesh",
        "camera",
        "light",
    } <= kinds
    (character,) = [p for p in report["prims"] if p["kind"] == "neuralCharacter"]
    assert "RigspaceCaptureRingAPI" in character["appliedSchemas"]
    assert character["values"]["rigspace:skeleton"]


def test_previs_scene_prints_the_tree_and_no_errors(capsys):
    code = main(["inspect", str(REPO / "samples" / "scenes" / "previs.usda")])
    out = capsys.readouterr().out
    assert code == 0
    assert "Validation: 0 errors" in out
    for word in ("neuralCharacter", "skeleton", "skinnedMesh", "camera", "light", "upAxis Y"):
        assert word in out


def test_cesium_man_usdz(capsys):
    code, report = inspect_json(CESIUM_MAN, capsys)
    assert report["stage"]["timeCodesPerSecond"] == 24
    # The shipped copy authors inputs:varname as a string (samples/assets/CesiumMan/NOTICE.md).
    assert report["errors"] == [] and code == 0
    (skeleton,) = [p for p in report["prims"] if p["kind"] == "skeleton"]
    (mesh,) = [p for p in report["prims"] if p["kind"] == "skinnedMesh"]
    (anim,) = [p for p in report["prims"] if p["kind"] == "skelAnimation"]
    assert skeleton["joints"] == 19
    assert (mesh["triangles"], mesh["influences"]) == (4672, 4)
    assert anim["timeRange"] == [1.0, 48.0]


def test_usdc(tmp_path, tiny_scene, capsys):
    usdc = tmp_path / "scene.usdc"
    assert Sdf.Layer.FindOrOpen(str(tiny_scene())).Export(str(usdc))
    code, report = inspect_json(usdc, capsys)
    assert code == 0, report["errors"]
    assert any(p["kind"] == "neuralCharacter" for p in report["prims"])


def test_broken_scene_names_its_errors_and_exits_1(tiny_scene, capsys):
    path = tiny_scene(
        character="        uniform int rigspace:captureRing:resolution = 100\n"
        "        uniform asset rigspace:model = @./nowhere@"
    )
    path.write_text(path.read_text().replace("rel rigspace:skeleton = </World/Asset/Skel>", ""))
    code = main(["inspect", str(path)])
    out = capsys.readouterr().out
    assert code == 1
    for code_name in ("NoSkeleton", "ResolutionNotPowerOfTwo", "ModelNotFound"):
        assert code_name in out
    assert out.count("/World/Hero") >= 3 and "Fix:" in out


@pytest.mark.parametrize(
    ("content", "suffix", "message"),
    [
        ('#usda 1.0\ndef Xform "A" {\n  over "B" { }\n', ".usda", "Expected }"),
        ("hello", ".txt", "not a USD file"),
        (None, ".usda", "does not exist"),
    ],
)
def test_unreadable_scene_is_a_clear_error(tmp_path, capsys, content, suffix, message):
    path = tmp_path / f"scene{suffix}"
    if content is not None:
        path.write_text(content)
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err
    assert message in err and str(path) in err and "Traceback" not in err


def test_a_text_file_named_usda_says_what_it_is_what_usd_said_and_the_fix(tmp_path, capsys):
    path = tmp_path / "notes.usda"
    path.write_text("shopping list\n- milk\n")
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"Scene {path} is not USD: it does not start with the `#usda 1.0` header" in err
    assert f"USD reports: <{path}> is not a valid usda layer." in err
    assert "Fix: export the scene to USD (.usda, .usdc or .usdz)" in err and err.endswith(".")


def _run(command: list[str]) -> subprocess.CompletedProcess:
    # PATH holds the system folders only: what a fresh clone has when pytest runs as
    # `.venv/bin/python -m pytest` without an activated environment.
    env = {"PATH": "/usr/bin:/bin", "HOME": str(Path.home())}
    return subprocess.run(command, capture_output=True, text=True, check=False, env=env)


def test_console_script():
    # Installed beside the interpreter, as pip puts console scripts: not looked up on PATH.
    exe = Path(sys.executable).parent / "rigspace"
    assert exe.is_file(), (
        f"the rigspace console script is not installed at {exe} (pip install -e .)"
    )
    result = _run([str(exe), "inspect", "--json", str(CESIUM_MAN)])
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["stage"]["upAxis"] == "Y"


def test_python_dash_m():
    result = _run([sys.executable, "-m", "rigspace.sdk", "inspect", "--json", str(CESIUM_MAN)])
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["stage"]["timeCodesPerSecond"] == 24


def test_the_readme_broken_fixture(capsys):
    code, report = inspect_json(REPO / "tests" / "fixtures" / "broken_character.usda", capsys)
    assert code == 1
    ours = {e["code"] for e in report["errors"] if e["validator"].startswith("rigspace:")}
    assert ours == {"NotASkeleton", "ModelNotFound", "ResolutionNotPowerOfTwo", "BadUrl"}


def test_an_unreadable_layer_is_named_by_inspect_and_refused_by_capture(tmp_path, capsys):
    """A reference to a truncated, an empty and a missing layer: inspect names each (no
    traceback from USD's validators) and capture refuses in the same words."""
    from rigspace.sdk import validation
    from rigspace.sdk.errors import SceneError
    from rigspace.sdk.stage import open_stage

    text = (REPO / "samples" / "scenes" / "cesium_man.usda").read_text()
    (tmp_path / "trunc.usda").write_text(text[:300])
    (tmp_path / "empty.usda").write_text("")
    scene = tmp_path / "scene.usda"
    scene.write_text(
        '#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n    upAxis = "Y"\n)\n'
        'def Xform "World"\n{\n'
        '    def "A" (prepend references = @./trunc.usda@) {}\n'
        '    def "B" (prepend references = @./empty.usda@) {}\n'
        '    def "C" (prepend references = @./gone.usda@) {}\n}\n'
    )
    assert main(["inspect", str(scene)]) == 1
    out = capsys.readouterr().out
    assert "@./trunc.usda@, which USD cannot read: a syntax error at line 7" in out
    assert "@./empty.usda@, which USD cannot read" in out
    assert "@./gone.usda@, which USD cannot read: it does not exist." in out
    with pytest.raises(SceneError, match=r"trunc\.usda"):
        validation.require_valid(open_stage(scene), "capture")


@pytest.mark.parametrize(
    "command",
    [
        ["capture", "--out", "{tmp}/ds"],
        ["capture", "--character", "/World/Hero", "--out", "{tmp}/ds"],
        ["render", "--out", "{tmp}/frames"],
    ],
    ids=["capture", "capture --character", "render"],
)
def test_capture_and_render_name_an_unreadable_sublayer_as_inspect_does(tmp_path, capsys, command):
    """The shot's character and camera live in a sublayer USD cannot read: USD composes
    around it, and capture said "0 neural characters ... pass --character" (or "There is no
    prim /World/Hero"), render "The stage has no Camera prim". Both name the layer now."""
    scene = tmp_path / "scene.usda"
    scene.write_text(
        '#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n    upAxis = "Y"\n'
        "    subLayers = [@./shot.usda@]\n)\n"
        'def Xform "World"\n{\n}\n'
    )
    argv = [command[0], str(scene), *(a.format(tmp=tmp_path) for a in command[1:])]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "@./shot.usda@, which USD cannot read: it does not exist." in err, err
    assert "neural characters" not in err and "no Camera prim" not in err
    assert not (tmp_path / "ds").exists() and not (tmp_path / "frames").exists()

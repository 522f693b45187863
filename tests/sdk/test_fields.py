"""The malformed corpus: every field rigspace reads from a bundle or dataset manifest given a
wrong type is one named error, from the reader and from the commands; never a traceback."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil

import pytest

from rigspace.capture.dataset import DATASET_MANIFEST, DatasetError
from rigspace.capture.dataset import read_manifest as read_dataset
from rigspace.sdk.bundle import BundleError, read_manifest
from rigspace.sdk.cli import main
from rigspace.sdk.fields import BUNDLE_MANIFEST, Field, Positive, Size, kind_of, spec_of
from tests.conftest import REPO

SAMPLE = REPO / "samples" / "models" / "sample"
WRONG = {
    "number": "far", "positive": "far", "count": "many", "size": "big", "text": 7,
    "names": "pelvis", "object": 7, "list": 7, "numbers": ["x"], "flag": "yes",
}  # fmt: skip


def broken(data: dict, field: Field) -> dict:
    """`data` with `field` (the first item of any list on its path) given a wrong type."""
    out = copy.deepcopy(data)
    parts = field.path.split(".")
    at = out
    for part in parts[:-1]:
        at = at[part.removesuffix("[]")]
        if part.endswith("[]"):
            at = at[0]
    last = parts[-1]
    if last.endswith("[]"):
        at[last.removesuffix("[]")][0] = WRONG[field.kind]
    else:
        at[last] = WRONG[field.kind]
    return out


def present(data: dict, field: Field) -> bool:
    at = data
    for part in field.path.split("."):
        key = part.removesuffix("[]")
        if not isinstance(at, dict) or key not in at:
            return False
        at = at[key][0] if part.endswith("[]") else at[key]
    return True


SAMPLE_MANIFEST = json.loads((SAMPLE / "manifest.json").read_text())
BUNDLE_FIELDS = [f for f in BUNDLE_MANIFEST if present(SAMPLE_MANIFEST, f)]


BLEND_FIELDS = ("blend_shapes", "torch.blend_shapes")
"""What a bundle of a character with blend shapes adds (the sample character has none)."""
REGION_FIELDS = (
    "regions", "regions[]", "regions[].name", "regions[].joint", "regions[].bundle",
    "training_camera.upright_axis",
)  # fmt: skip
"""What a bundle with regions adds, and a region's bundle whose cameras kept its joint upright
(docs/regions.md; the sample bundle has neither)."""
CONTROL_FIELDS = (
    "controls", "controls[]", "controls[].name", "controls[].range", "torch.controls",
)  # fmt: skip
"""What a bundle of a rig with named controls adds (docs/point_caches.md; the sample has none)."""
VIEW_FIELDS = ("views", "views.file", "views.joint", "views.elevations")
"""What a bundle exported with its training views adds (sdk.view_coverage; the sample bundle,
exported before them, has none)."""


def test_the_sample_bundle_has_almost_every_field():
    added = BLEND_FIELDS + REGION_FIELDS + CONTROL_FIELDS + VIEW_FIELDS
    others = [f for f in BUNDLE_MANIFEST if f.path not in added]
    assert len(BUNDLE_FIELDS) >= len(others) - 2  # all but capsules' text etc.


@pytest.mark.parametrize(
    "path",
    [p for p in CONTROL_FIELDS if p != "controls[]"]
    + list(VIEW_FIELDS)
    + ["training_camera.upright_axis"],
)
def test_a_wrong_type_in_a_control_or_views_field_is_a_named_error(tmp_path, path):
    data = copy.deepcopy(SAMPLE_MANIFEST)
    data["controls"] = [{"name": "bulge", "range": [0.0, 1.0]}]
    data["torch"]["controls"] = 1
    data["views"] = {"file": "views.npy", "joint": 0, "elevations": [0.0, 20.0]}
    data["training_camera"]["upright_axis"] = [0.0, 1.0, 0.0]
    field = next(f for f in BUNDLE_MANIFEST if f.path == path)
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text(json.dumps(broken(data, field)))
    with pytest.raises(BundleError, match="Fix:") as info:
        read_manifest(bundle)
    assert f"'{path.replace('[]', '[0]').removesuffix('[0]')}" in str(info.value)


@pytest.mark.parametrize("axis", [[0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 1e400, 0.0]])
def test_an_upright_axis_that_is_no_direction_is_a_named_error(tmp_path, axis):
    data = copy.deepcopy(SAMPLE_MANIFEST)
    data["training_camera"]["upright_axis"] = axis
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text(json.dumps(data).replace("Infinity", "1e400"))
    with pytest.raises(BundleError, match=r"upright_axis.? is .*(three finite|not a list)"):
        read_manifest(bundle)


@pytest.mark.parametrize(
    ("controls", "said"),
    [
        ([{"name": "bulge", "range": [1.0, 0.0]}], "does not have low < high"),
        ([{"name": "bulge", "range": [0.0]}], "is not two finite numbers"),
        ([{"name": "bulge", "range": [0, 1]}] * 2, "is listed twice"),
    ],
)
def test_a_bad_control_in_a_bundle_is_a_named_error(tmp_path, controls, said):
    data = copy.deepcopy(SAMPLE_MANIFEST) | {"controls": controls}
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(BundleError, match=said):
        read_manifest(bundle)


def test_a_bundle_without_controls_reads_none():
    """A bundle exported before controls (the committed sample) reads exactly as before."""
    manifest = read_manifest(SAMPLE)
    assert manifest.controls == () and "controls" not in SAMPLE_MANIFEST


@pytest.mark.parametrize(("path", "value"), [("blend_shapes", "smile"), ("torch.blend_shapes", -1)])
def test_a_wrong_type_in_a_blend_shape_field_is_a_named_error(tmp_path, path, value):
    data = copy.deepcopy(SAMPLE_MANIFEST)
    if "." in path:
        data["torch"]["blend_shapes"] = value
    else:
        data[path] = value
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(BundleError, match=f"'{path}' is {value!r}"):
        read_manifest(bundle)


@pytest.mark.parametrize("field", BUNDLE_FIELDS, ids=lambda f: f.path)
def test_a_wrong_type_in_a_bundle_manifest_is_a_named_error(tmp_path, field):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text(json.dumps(broken(SAMPLE_MANIFEST, field)))
    with pytest.raises(BundleError) as info:
        read_manifest(bundle)
    shown = field.path.replace("[]", "[0]").removesuffix("[0]")
    assert f"'{shown}" in str(info.value) and "Fix:" in str(info.value)


@pytest.mark.parametrize(
    "path", ["training_camera.distance", "levels", "levels[].resolution", "depth.scale"]
)
def test_render_and_eval_name_the_field_and_leave_no_output(tmp_path, capsys, path):
    field = next(f for f in BUNDLE_MANIFEST if f.path == path)
    bundle = tmp_path / "bundle"
    shutil.copytree(SAMPLE, bundle, ignore=shutil.ignore_patterns("training"))
    (bundle / "manifest.json").write_text(json.dumps(broken(SAMPLE_MANIFEST, field)))
    scene = REPO / "samples" / "scenes" / "previs.usda"
    out = tmp_path / "frames"
    code = main(["render", str(scene), "--model", str(bundle), "--out", str(out), "--frames",
                 "300:300", "--resolution", "64x36"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and path.split("[")[0].split(".")[0] in err
    assert not out.exists()


def test_a_wrong_type_in_a_dataset_manifest_is_a_named_error(tmp_path, tiny_dataset):
    manifest = json.loads((tiny_dataset / "manifest.json").read_text())
    # A rig with named controls adds its `controls` (docs/point_caches.md; the tiny one has none).
    manifest["controls"] = [{"name": "bulge", "range": [0.0, 1.0]}]
    fields = [f for f in DATASET_MANIFEST if present(manifest, f)]
    assert len(fields) >= len(DATASET_MANIFEST) - 2
    assert {f.path for f in fields} >= {"controls", "controls[].name", "controls[].range"}
    for field in fields:
        folder = tmp_path / field.path.replace("[]", "-each")  # clips and clips[]: two folders
        folder.mkdir()
        (folder / "manifest.json").write_text(json.dumps(broken(manifest, field)))
        shutil.copy(tiny_dataset / "params.npz", folder / "params.npz")
        with pytest.raises(DatasetError, match="Fix:") as info:
            read_dataset(folder)
        assert field.path.split("[")[0].split(".")[0] in str(info.value)


def test_a_wrong_type_in_run_json_or_capture_json_is_a_named_error(tmp_path, tiny_dataset):
    from rigspace.capture.pipeline import CaptureError, prepare_folder
    from rigspace.capture.settings import CaptureSettings
    from rigspace.sdk.fields import CAPTURE_SETTINGS
    from rigspace.train.loop import TRAINING_RUN, TrainingError, read_run

    run = {
        "config": {},
        "dataset": "/d",
        "joints": ["a"],
        "charts": 2,
        "plan": {"steps_per_level": 5},
    }
    for field in TRAINING_RUN:
        if not present(run, field):
            continue
        folder = tmp_path / "run" / field.path
        folder.mkdir(parents=True)
        (folder / "run.json").write_text(json.dumps(broken(run, field)))
        with pytest.raises(TrainingError, match="Fix:") as info:
            read_run(folder)
        assert f"'{field.path}'" in str(info.value)
    (folder / "run.json").write_text("{not json")
    with pytest.raises(TrainingError, match="not readable JSON"):
        read_run(folder)
    settings = json.loads((tiny_dataset / "capture.json").read_text())
    for field in (f for f in CAPTURE_SETTINGS if present(settings, f)):
        folder = tmp_path / "capture" / field.path.replace("[]", "")
        folder.mkdir(parents=True)
        (folder / "capture.json").write_text(json.dumps(broken(settings, field)))
        with pytest.raises(CaptureError, match="Fix:") as info:
            prepare_folder(folder, CaptureSettings.from_json(settings), True, False)
        assert field.path.split("[")[0] in str(info.value)


@pytest.mark.parametrize(
    ("value", "said"),
    [
        ("3", '"3" (a string)'),
        (2.0, "2.0 (a decimal number)"),
        (True, "true (a boolean)"),
        (None, "missing"),
    ],
)
def test_a_format_version_that_is_not_an_integer_says_so(tmp_path, value, said):
    """A version "3" is not version 3 (nor 2.0 version 2, nor true version 1): the error says it
    must be an integer and what the manifest holds, not that this rigspace reads 1, 2, 3."""
    data = copy.deepcopy(SAMPLE_MANIFEST)
    if value is None:
        del data["format_version"]
    else:
        data["format_version"] = value
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(BundleError) as info:
        read_manifest(bundle)
    text = str(info.value)
    assert f"format_version must be an integer (one of 1, 2, 3, 4); it is {said}." in text
    assert "Fix:" in text


# -- one description: specs from the formats' dataclasses ----------------------------------------


@pytest.mark.parametrize(
    ("hint", "kind"),
    [
        (str, "text"), (bool, "flag"), (int, "count"), (float, "number"), (Size, "size"),
        (Positive | None, "positive"), (str | None, "text"), (tuple[str, ...], "names"),
        (tuple[float, ...], "numbers"), (tuple[Size, ...], "numbers"),
        (dict[str, int], "object"), (dict, "object"),
    ],
)  # fmt: skip
def test_a_fields_type_gives_its_kind(hint, kind):
    assert kind_of(hint) == (kind, None)


def test_a_section_or_a_list_of_sections_is_followed_into():
    from rigspace.capture.dataset import ManifestRing, ManifestView

    assert kind_of(ManifestRing | None) == ("object", ManifestRing)
    assert kind_of(tuple[ManifestView, ...]) == ("list", ManifestView)
    with pytest.raises(TypeError, match="annotate the field"):
        kind_of(frozenset[str])


def test_the_dataset_and_run_specs_are_their_dataclasses():
    """Every field of DatasetManifest (and its sections) and of RunRecord is in the spec, of
    its type's kind, required exactly when it has no default."""
    from rigspace.capture.dataset import DatasetManifest
    from rigspace.train.loop import TRAINING_RUN, RunRecord

    assert Field("ring", "object", required=True) in DATASET_MANIFEST
    assert Field("ring.radius", "positive", required=True) in DATASET_MANIFEST
    assert Field("ring.views[].held_out", "flag", required=True) in DATASET_MANIFEST
    assert Field("clips[].held_out", "flag") in DATASET_MANIFEST
    assert Field("meters_per_unit", "positive") in DATASET_MANIFEST
    assert Field("renderer.samples_per_axis", "size", required=True) in DATASET_MANIFEST
    paths = {f.path for f in DATASET_MANIFEST}
    unkeyed = {"path", "format", "format_version"}  # no key, or checked before the spec
    keys = {f.name for f in dataclasses.fields(DatasetManifest)} - unkeyed
    assert keys <= paths and "path" not in paths
    assert [f.path for f in TRAINING_RUN if f.required] == ["config", "dataset", "joints",
                                                            "controls[].name", "controls[].range",
                                                            "plan.steps_per_level"]  # fmt: skip
    assert {f.name for f in dataclasses.fields(RunRecord)} <= {f.path for f in TRAINING_RUN}


def test_the_bundle_spec_agrees_with_model_manifest_where_its_fields_are_keys():
    """BUNDLE_MANIFEST is written out (ModelManifest is a typed view, see sdk.fields); where a
    ModelManifest field (or a field of its sections) names a key, the kinds and the
    requirement agree, so the two descriptions cannot drift apart unseen."""
    from rigspace.sdk.bundle import ModelManifest

    # regions: each entry's `bundle` (text) is typed as the folder it names (RegionBundle.folder).
    derived = spec_of(ModelManifest, skip=("path", "int8_failed", "regions"))
    written = {f.path: f for f in BUNDLE_MANIFEST}
    shared = [f for f in derived if f.path in written]
    assert {f.path for f in shared} >= {"joints", "maps", "levels[].resolution", "texture.charts",
                                        "texture.branch", "torch", "files", "capsules"}  # fmt: skip
    assert [f for f in shared if written[f.path] != f] == []

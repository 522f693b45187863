"""A character with a face region, captured and trained in seconds, for the runtime's tests.

The blend shape character (tests/blendshapes.py: a 2-unit cylinder skinned to neck and head)
with RigspaceRegionAPI:face on its head joint: a 0.8-unit square at 32x32, its cameras upright
to the head (`upright = "joint"`), so that from the scene's camera (5 units away) the body's
billboard is magnified and the face adds detail.
Captured small (2 views, every 6th frame, the body at 32x32) and trained with the tiny preset
for 3 steps (levels 8 and 16 of each bundle; about 10 s), once per test session. The skinned
asset is then made a guide, so that frames show the network's character.
"""

from __future__ import annotations

from pathlib import Path

from rigspace.sdk.cli import main
from tests.blendshapes import write_blendshape_character
from tests.capture.test_regions import _with_region

_trained: dict[str, tuple[Path, Path]] = {}


def trained_regions(tmp_path_factory) -> tuple[Path, Path]:
    """(scene, bundle): the scene's character draws with the bundle (its rigspace:model), which
    lists the face region in regions/face."""
    if "face" not in _trained:
        folder = tmp_path_factory.mktemp("regions_model")
        scene = write_blendshape_character(folder)
        _with_region(scene, joint="head", resolution=32, size=0.8, upright="joint")
        dataset, bundle = folder / "ds", folder / "model"
        capture = ["capture", str(scene), "--out", str(dataset), "--views", "2", "--every", "6",
                   "--resolution", "32", "--workers", "1", "--regions"]  # fmt: skip
        assert main(capture) == 0
        train = ["train", str(dataset), "--out", str(bundle), "--preset", "tiny", "--steps", "3",
                 "--no-int8"]  # fmt: skip
        assert main(train) == 0
        from pxr import Usd, UsdGeom

        from tests.blendshapes import CHARACTER

        stage = Usd.Stage.Open(str(scene))
        stage.GetPrimAtPath(CHARACTER).GetAttribute("rigspace:model").Set(str(bundle))
        # The skinned asset lies outside the character prim: a guide, which the runtime does
        # not draw as a scene prim, so that frames show the network's character (the rig and
        # --reference's mesh still read it).
        UsdGeom.Imageable(stage.GetPrimAtPath("/World/Asset")).CreatePurposeAttr("guide")
        stage.GetRootLayer().Save()
        _trained["face"] = (scene, bundle)
    return _trained["face"]


def ring_rows(part, pose, table, rows):
    """For each of `rows` of a dataset's params table, the camera that captured it put in the
    stage: (the part's network input there (1, J*6 + ...), the recorded rig row (J*6,), the
    part's billboard). `pose(time)` gives the character's joints (NeuralCharacter.pose)."""
    from rigspace.sdk.camera import Camera

    for k in rows:
        size = round(2 * table["intrinsics"][k][2])
        camera = Camera(table["camera_to_world"][k], size, size,
                        focal_length=part.view.focal_length,
                        horizontal_aperture=part.view.horizontal_aperture)  # fmt: skip
        world = pose(float(table["time"][k]))
        billboard = part.place(world, camera)
        yield part.parameters(world, billboard, camera), table["rig"][k].reshape(-1), billboard

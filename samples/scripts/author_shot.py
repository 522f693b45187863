"""Author a neural character into a new stage and render a shot of it.

    python samples/scripts/author_shot.py --out out/shot [--frames 0:90:15]

Writes OUT/shot.usda (centimetres, Y up, 30 fps): a ground, a crate, a sun and a sky, a
still camera, and the sample character as a RigspaceNeuralCharacter drawn by the committed
sample model bundle (samples/models/sample); then renders the frames with the Engine into
OUT/shot_*.png and prints what each frame cost. `rigspace inspect OUT/shot.usda` validates
the stage and `rigspace render OUT/shot.usda --out DIR` renders it the same way.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.sdk.color import linear_to_srgb

SAMPLES = Path(__file__).resolve().parents[1]


def author(path: Path) -> Usd.Stage:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetTimeCodesPerSecond(30)
    stage.SetFramesPerSecond(30)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(359)  # the sample character's walk clip
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())

    # The neural character: the sample character's asset (skeleton, animation, skinned mesh)
    # under a RigspaceNeuralCharacter that names its skeleton and the model bundle.
    hero = stage.DefinePrim("/World/Hero", "RigspaceNeuralCharacter")
    asset = stage.DefinePrim("/World/Hero/Asset")
    asset.GetReferences().AddReference(str(SAMPLES / "character" / "sample_character.usda"))
    hero.CreateRelationship("rigspace:skeleton", custom=False).SetTargets(
        [Sdf.Path("/World/Hero/Asset/Skel")]
    )
    model = hero.CreateAttribute("rigspace:model", Sdf.ValueTypeNames.Asset, custom=False,
                                 variability=Sdf.VariabilityUniform)  # fmt: skip
    model.Set(Sdf.AssetPath(str(SAMPLES / "models" / "sample")))
    look = hero.CreateAttribute("rigspace:lookAtJoint", Sdf.ValueTypeNames.Token, custom=False,
                                variability=Sdf.VariabilityUniform)  # fmt: skip
    look.Set("pelvis")

    ground = UsdGeom.Mesh.Define(stage, "/World/Set/Ground")
    ground.CreatePointsAttr([(-800, 0, 800), (800, 0, 800), (800, 0, -800), (-800, 0, -800)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    ground.CreateExtentAttr([(-800, 0, -800), (800, 0, 800)])
    ground.CreateDisplayColorAttr([(0.3, 0.32, 0.28)])
    crate = UsdGeom.Cube.Define(stage, "/World/Set/Crate")
    crate.CreateSizeAttr(60)
    crate.AddTranslateOp().Set(Gf.Vec3d(-120, 30, -150))
    crate.CreateDisplayColorAttr([(0.8, 0.55, 0.3)])

    sun = UsdLux.DistantLight.Define(stage, "/World/Lights/Sun")
    sun.CreateIntensityAttr(2.5)
    sun.CreateAngleAttr(0.53)
    sun.AddRotateXYZOp().Set(Gf.Vec3f(-50, 35, 0))
    sky = UsdLux.DomeLight.Define(stage, "/World/Lights/Sky")
    sky.CreateColorAttr(Gf.Vec3f(0.6, 0.75, 1.0))
    sky.CreateIntensityAttr(0.5)

    camera = UsdGeom.Camera.Define(stage, "/World/Camera")
    camera.CreateFocalLengthAttr(24)
    camera.CreateHorizontalApertureAttr(20.955)
    camera.CreateVerticalApertureAttr(11.787)
    camera.CreateClippingRangeAttr(Gf.Vec2f(10, 10000))
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 150, 700))
    camera.AddRotateXOp().Set(-6.0)
    stage.GetRootLayer().Save()
    return stage


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder for shot.usda and the frames")
    parser.add_argument("--frames", default="0:90:15", help="FIRST:LAST:STEP time codes")
    parser.add_argument("--size", default="480x270", help="WxH")
    args = parser.parse_args()
    first, last, step = (float(v) for v in args.frames.split(":"))
    width, height = (int(v) for v in args.size.split("x"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    author(out / "shot.usda")
    with Engine(out / "shot.usda", EngineSettings(width=width, height=height)) as engine:
        for t in np.arange(first, last + step / 2, step):
            frame = engine.render(float(t))
            hero = frame.report.characters[0]
            print(f"frame {t:g}: {hero['decision']}, level {hero.get('level')}, "
                  f"{1e3 * frame.report.seconds['total']:.0f} ms")  # fmt: skip
            rgb = (linear_to_srgb(frame.beauty) * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(out / f"shot_{t:05.0f}.png"), rgb[..., ::-1])


if __name__ == "__main__":
    main()

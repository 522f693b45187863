"""Does the runtime lose accuracy that the model itself does not? Neural frame against mesh, per map.

The model's own error is what `rigspace eval` measures: the network's maps at a ring
camera (rig parameters in that camera's frame) against the mesh drawn there. The runtime
adds the rest of the paper's scene composition: the billboard's placement, the off-centre
rotation R, the warp into the frame and the composite. This measures both on the same
samples (held-out ring views at frames spread over the scene's clips), in three framings
of the same character through the whole `Engine` (neural) and `Engine(reference=True)`
(the real skinned mesh, drawn by the renderer):

- centred: the ring camera itself, training resolution (s = 1, R = I, the warp is the
  identity): any loss here is a bug in the runtime's plumbing;
- off-centre: that camera turned 15 degrees right and 10 up in a frame twice as large,
  so the billboard sits off the image centre (R is not I, the warp is not the identity);
- far: twice the distance with twice the focal length (the same size on screen, s = 2;
  the flatter perspective is what a billboard cannot reproduce).

Each map is compared over the billboard's region, as eval compares whole training
images: albedo PSNR (premultiplied), mask IoU, normal mean angle (render-camera frame),
depth MAE in % of the character's height. The scene's other prims are deactivated and no
beauty is asked for, so the comparison is of the character alone, unlit. The runtime draws
the albedo branch here (`textures=False`), the map the model's own row measures (its colour
premultiplied by the geometry's mask, as the runtime premultiplies it: sdk.texturing
`repremultiplied`); what the character's textures change at display size is the bench's
`texture` part.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Gf, Usd, UsdGeom

from rigspace.capture.settings import resolve_settings
from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.runtime.scene import SceneGeometry
from rigspace.sdk import schema
from rigspace.sdk.camera import Camera, to_gf
from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import Maps, RenderSettings, choose_renderer
from rigspace.sdk.rotations import rig_parameters
from rigspace.sdk.stage import overlay_layer
from rigspace.sdk.texturing import repremultiplied
from rigspace.train.metrics import map_metrics
from rigspace.train.predictor import to_maps

ROOT = Path(__file__).resolve().parents[1]
PREVIS = ROOT / "samples" / "scenes" / "previs.usda"
FRAMINGS = ("centred", "off-centre", "far")
AOVS = ("albedo", "normal", "depth", "mask")
COMPARED = ("albedo_psnr", "mask_iou", "normal_mean_deg", "depth_mae_pct")
OFF_CENTRE_DEG = (15.0, 10.0)
"""(yaw right, pitch up) of the off-centre framing's camera, degrees."""


def _turned(camera: Camera, yaw_deg: float, pitch_deg: float, scale: int) -> Camera:
    """The camera turned about its own axes, in a frame `scale` times larger (same pixels/unit)."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    ry = np.array([[np.cos(yaw), 0, -np.sin(yaw)], [0, 1, 0], [np.sin(yaw), 0, np.cos(yaw)]])
    rx = np.array(
        [[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]]
    )
    pose = camera.camera_to_world.copy()
    pose[:3, :3] = pose[:3, :3] @ ry @ rx
    return Camera(
        pose,
        camera.width * scale,
        camera.height * scale,
        camera.focal_length,
        camera.horizontal_aperture * scale,
        near=camera.near,
        far=camera.far,
    )


def _farther(camera: Camera, target: np.ndarray, factor: float) -> Camera:
    pose = camera.camera_to_world.copy()
    pose[:3, 3] = target + factor * (pose[:3, 3] - target)
    return Camera(
        pose,
        camera.width,
        camera.height,
        camera.focal_length * factor,
        camera.horizontal_aperture,
        near=camera.near,
        far=camera.far * factor,
    )


def _framing_layer(folder: Path, scene: Path, cameras: dict[str, list[tuple[float, Camera]]]):
    """A layer over `scene`: its drawn prims deactivated, one time-sampled camera per framing."""
    layer = overlay_layer(folder / "accuracy.usda", scene)
    stage = Usd.Stage.Open(layer)
    for prim in SceneGeometry(stage).prims:
        stage.OverridePrim(prim.GetPath()).SetActive(False)
    for name, samples in cameras.items():
        camera = UsdGeom.Camera.Define(stage, f"/AccuracyCameras/{name.replace('-', '_')}")
        first = samples[0][1]
        camera.CreateFocalLengthAttr(first.focal_length)
        camera.CreateHorizontalApertureAttr(first.horizontal_aperture)
        camera.CreateVerticalApertureAttr(first.horizontal_aperture * first.height / first.width)
        camera.CreateClippingRangeAttr(Gf.Vec2f(first.near, first.far))
        op = camera.AddTransformOp()
        for time, cam in samples:
            op.Set(to_gf(cam.camera_to_world), Usd.TimeCode(time))
    layer.Save()
    return folder / "accuracy.usda"


def _crop(maps: Maps, region: list[int]) -> Maps:
    x, y, w, h = region
    s = np.s_[y : y + h, x : x + w]
    return Maps(maps.albedo[s], maps.normal[s], maps.depth[s], maps.mask[s])


def measure(
    scene: str | Path = PREVIS,
    character: str = "/World/Hero",
    samples: int = 12,
    precision: str = "fp32",
    out_dir: str | Path | None = None,
) -> dict[str, Any]:
    """The model's own error and the runtime's, per framing, on the same held-out samples.

    Returns {"samples": [...], "framings": {name: {"model": means, "runtime": means,
    "delta": model - runtime}}}; means over the samples of COMPARED. With `out_dir`, one
    image per framing: neural | reference | 4x albedo error, a row per sample.
    """
    scene = Path(scene)
    settings, rig = resolve_settings(scene, character)
    prim = rig.skeleton.GetPrim().GetStage().GetPrimAtPath(character)
    model = BundleModel(
        schema.resolve_model_path(schema.read_neural_character(prim)), precision=precision
    )
    own = _model_error(settings, rig, model, samples)
    result: dict[str, Any] = {"samples": own.picked, "framings": {}}
    with tempfile.TemporaryDirectory() as tmp:
        layer = _framing_layer(Path(tmp), scene, own.cameras)
        for name, samples_ in own.cameras.items():
            rows, strips = _runtime_error(layer, name, samples_, precision, prim, own.height)
            mine = _means(own.rows)
            theirs = _means(rows)
            result["framings"][name] = {
                "model": mine,
                "runtime": theirs,
                "delta": {k: mine[k] - theirs[k] for k in COMPARED},
                "per_sample_albedo_psnr": [r["albedo_psnr"] for r in rows],
            }
            if out_dir is not None:
                _write_sheet(Path(out_dir) / f"accuracy_{name}.png", strips)
    return result


@dataclass(frozen=True)
class _ModelError:
    """The model's own error per held-out sample, and the framings' cameras at those samples."""

    picked: list[dict[str, float]]
    """Each sample's time and ring view."""
    cameras: dict[str, list[tuple[float, Camera]]]
    """Per framing, (time, camera) of each sample."""
    rows: list[dict[str, float]]
    """map_metrics of the network's maps against the mesh, per sample."""
    height: float
    """The character's height (along the first sample's view's up), for the depth metric."""


def _model_error(settings, rig, model: BundleModel, samples: int) -> _ModelError:
    """The model's maps at held-out ring views (at frames spread over the scene's clips)
    against the mesh drawn there, as `rigspace eval` measures them; and each framing's camera."""
    order = [schema.find_joint(j, rig.joints) for j in model.joints]
    look_at = schema.find_joint(settings.look_at_joint, rig.joints)
    held_out = [v for v in settings.views() if v.held_out]
    clips = [c for c in settings.clips if not c.held_out]
    span = np.concatenate([c.times() for c in clips])
    times = span[np.linspace(0, len(span) - 1, samples).astype(int)]
    renderer = choose_renderer("auto").create(RenderSettings())
    picked: list[dict[str, float]] = []
    cameras: dict[str, list[tuple[float, Camera]]] = {name: [] for name in FRAMINGS}
    model_rows = []
    height = None
    try:
        for k, time in enumerate(times):
            view = held_out[(k * 5) % len(held_out)]  # spread over azimuths and elevations
            world = rig.world_transforms(float(time))
            joint = world[look_at][:3, 3]
            camera = view.camera(joint, settings.lens, settings.camera_up(world[look_at]))
            truth = renderer.render(rig.posed_meshes(float(time)), camera)
            if height is None:
                points = np.concatenate([m.points for m in rig.posed_meshes(float(time))])
                height = float(np.ptp(points @ view.up))
            rig_q = rig_parameters(world[order], camera.camera_to_world).reshape(1, -1)
            out = model.predict(rig_q, settings.resolution)
            if "alpha" in out:  # the colour as the runtime makes it: premultiplied by the mask
                alpha, mask = np.clip(out["alpha"][:, 0], 0, 1), np.clip(out["mask"][:, 0], 0, 1)
                albedo = np.moveaxis(np.clip(out["albedo"], 0, 1), 1, -1)
                out = {**out, "albedo": np.moveaxis(repremultiplied(albedo, alpha, mask), -1, 1)}
            joint_depth = np.array([-camera.to_camera(joint[None])[0, 2]])
            (maps,) = to_maps(out, joint_depth, model.depth_scale)  # as `rigspace eval` reads them
            model_rows.append(map_metrics(maps, truth, height))
            picked.append({"time": float(time), "view": view.index, "azimuth": view.azimuth,
                           "elevation": view.elevation})  # fmt: skip
            cameras["centred"].append((float(time), camera))
            cameras["off-centre"].append((float(time), _turned(camera, *OFF_CENTRE_DEG, 2)))
            cameras["far"].append((float(time), _farther(camera, joint, 2.0)))
    finally:
        renderer.close()
    assert height is not None
    return _ModelError(picked, cameras, model_rows, height)


def _runtime_error(
    layer: Path,
    name: str,
    samples: list[tuple[float, Camera]],
    precision: str,
    prim: Usd.Prim,
    height: float,
) -> tuple[list[dict[str, float]], list[np.ndarray]]:
    """One framing through the whole Engine, neural against reference, over the character's
    region: (map_metrics per sample, an image strip per sample)."""
    path = f"/AccuracyCameras/{name.replace('-', '_')}"
    size = {"width": samples[0][1].width, "height": samples[0][1].height}
    neural = Engine(
        layer, EngineSettings(camera=path, precision=precision, aovs=AOVS, textures=False, **size)
    )
    truth_engine = Engine(layer, EngineSettings(camera=path, reference=True, aovs=AOVS, **size))
    rows, strips = [], []
    try:
        for time, _ in samples:
            frame = neural.render(time)
            truth_frame = truth_engine.render(time)
            region = next(
                c["region"] for c in frame.report.characters if c["path"] == str(prim.GetPath())
            )
            a, b = _crop(frame.maps, region), _crop(truth_frame.maps, region)
            rows.append(map_metrics(a, b, height))
            strips.append(_strip(a.albedo, b.albedo))
    finally:
        neural.close()
        truth_engine.close()
    return rows, strips


def _means(rows: list[dict[str, float]]) -> dict[str, float]:
    return {k: float(np.nanmean([r[k] for r in rows])) for k in COMPARED}


def _strip(neural: np.ndarray, reference: np.ndarray) -> np.ndarray:
    import cv2

    from rigspace.sdk.color import linear_to_srgb

    size = (128, 128)
    tiles = [
        linear_to_srgb(np.clip(neural, 0, 1)),
        linear_to_srgb(np.clip(reference, 0, 1)),
        np.clip(4 * np.abs(neural - reference), 0, 1),
    ]
    return np.concatenate([cv2.resize(t.astype(np.float32), size) for t in tiles], axis=1)


def _write_sheet(path: Path, strips: list[np.ndarray]) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    sheet = np.concatenate(strips, axis=0)
    cv2.imwrite(str(path), (sheet * 255 + 0.5).astype(np.uint8)[..., ::-1])


def format_table(result: dict[str, Any]) -> str:
    lines = [
        "| framing | albedo PSNR model / runtime (delta) | mask IoU | normal mean deg | depth % height |",
        "|---|---|---|---|---|",
    ]
    for name, row in result["framings"].items():
        m, r = row["model"], row["runtime"]
        lines.append(
            f"| {name} | {m['albedo_psnr']:.2f} / {r['albedo_psnr']:.2f} ({m['albedo_psnr'] - r['albedo_psnr']:+.2f} dB) "
            f"| {m['mask_iou']:.3f} / {r['mask_iou']:.3f} | {m['normal_mean_deg']:.1f} / {r['normal_mean_deg']:.1f} "
            f"| {m['depth_mae_pct']:.2f} / {r['depth_mae_pct']:.2f} |"
        )
    return "\n".join(lines)

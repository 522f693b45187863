"""The runtime engine: a USD stage's frame with its neural characters drawn by their networks.

    engine = Engine("samples/scenes/previs.usda", width=640, height=360)
    frame = engine.render(120.0)        # named images plus a report of what it computed

Per frame: the camera at t; the scene's other prims drawn by the renderer plugin into a
G-buffer (reused while neither they nor the camera move); per neural character the pose,
its billboard, and (when visible) its network maps in the billboard's region, reused when
pose and camera repeat; each layer lit by the scene's lights (runtime/shading.py); then a
depth test composites the character over or under the prims, with its coverage as alpha
at its edges. Every decision and every stage's time goes into the frame's report. A
stage without lights renders unlit (beauty = albedo). Imports no torch.
"""

from __future__ import annotations

import hashlib
import sys
import time as clock
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Usd, UsdGeom

from rigspace.runtime.character import Layer, NeuralCharacter
from rigspace.runtime.lights import light_prims, lights_at
from rigspace.runtime.scene import SceneGeometry
from rigspace.runtime.shading import shade
from rigspace.sdk import schema
from rigspace.sdk.camera import Camera
from rigspace.sdk.errors import SceneError
from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import Maps, RenderSettings, choose_renderer, empty_maps
from rigspace.sdk.stage import open_stage

STAGES = ("scene", "rig", "network", "lighting", "composite")


@dataclass
class Frame:
    """One rendered frame: premultiplied beauty and the composited maps, plus its report."""

    beauty: np.ndarray
    """(H, W, 3) lit colour, premultiplied by `mask`."""
    maps: Maps
    report: dict[str, Any] = field(default_factory=dict)


@dataclass
class _CachedLayer:
    key: bytes
    layer: Layer
    lit: np.ndarray | None = None
    lit_key: bytes = b""
    """The lights `lit` was shaded with: lights that change re-light a reused layer."""


class Engine:
    """Opens a stage, loads its neural characters' bundles, renders frames for one camera."""

    def __init__(
        self,
        scene: str | Path,
        *,
        camera: str | None = None,
        width: int = 640,
        height: int = 360,
        renderer: str = "auto",
        precision: str = "fp32",
        reference: bool = False,
    ) -> None:
        """`reference=True` draws each character's real skinned mesh with the renderer instead
        of its network (the ground truth that `rigspace render --reference` compares with)."""
        if width <= 0 or height <= 0:
            raise SceneError(
                f"The viewport is {width}x{height}.",
                "render at least 1x1 pixels (--resolution WxH).",
            )
        self.stage: Usd.Stage = open_stage(scene)
        self.width, self.height = width, height
        self.camera_prim = self._camera(camera)
        self.characters: list[NeuralCharacter] = []
        self.without_model: list[str] = []
        models: dict[Path, BundleModel] = {}
        for prim in schema.neural_characters(self.stage):
            manifest = schema.resolve_model_path(schema.read_neural_character(prim))
            if manifest is None:
                self.without_model.append(str(prim.GetPath()))
                continue
            folder = manifest.parent.resolve()
            if folder not in models:  # characters sharing a bundle share its sessions
                models[folder] = BundleModel(folder, precision)
                if not reference:
                    models[folder].preload()  # a damaged bundle fails here, not mid-sequence
            self.characters.append(NeuralCharacter(prim, models[folder]))
        self.reference = reference
        self.scene = SceneGeometry(self.stage)
        self.light_prims = light_prims(self.stage)
        self.renderer = choose_renderer(renderer).create(RenderSettings())
        self._prims_key: tuple = ()
        self._prims: Maps | None = None
        self._layers: dict[str, _CachedLayer] = {}
        self._lit_prims: tuple[bytes, np.ndarray] | None = None

    def _camera(self, path: str | None) -> Usd.Prim:
        if path:
            prim = self.stage.GetPrimAtPath(path)
            if not prim or not prim.IsA(UsdGeom.Camera):
                raise SceneError(
                    f"{path} is not a Camera prim of the stage.",
                    "pass --camera with a Camera's path.",
                )
            return prim
        cameras = [p for p in self.stage.Traverse() if p.IsA(UsdGeom.Camera)]
        if not cameras:
            raise SceneError(
                "The stage has no Camera prim.", "add a UsdGeom.Camera or pass --camera."
            )
        return cameras[0]

    def close(self) -> None:
        self.renderer.close()

    def _scene_maps(self, meshes, camera: Camera) -> tuple[Maps, bool]:
        key = (tuple(id(m) for m in meshes), _camera_key(camera))
        if self._prims is not None and key == self._prims_key:
            return self._prims, True
        maps = (
            self.renderer.render(meshes, camera)
            if meshes
            else empty_maps(camera.height, camera.width)
        )
        self._prims, self._prims_key = maps, key
        return maps, False

    def render(self, time: float) -> Frame:
        timings = dict.fromkeys(STAGES, 0.0)
        start = clock.perf_counter()
        camera = Camera.from_usd(self.camera_prim, time, self.width, self.height)
        meshes = self.scene.meshes(time)
        if self.reference:
            meshes = meshes + [m for c in self.characters for m in c.rig.posed_meshes(time)]
        prims, reused = self._scene_maps(meshes, camera)
        timings["scene"] = clock.perf_counter() - start
        lights = lights_at(self.light_prims, time)
        report: dict[str, Any] = {
            "time": time,
            "camera": str(self.camera_prim.GetPath()),
            "scene_prims": {"meshes": len(meshes), "reused": reused},
            "lights": len(lights),
            "characters": [],
        }
        report["characters"] += [
            {"path": p, "decision": "skipped", "reason": "no model bundle (rigspace:model)"}
            for p in self.without_model
        ]
        t = clock.perf_counter()
        light_key = b"".join(
            light.radiance.tobytes() + light.direction.tobytes() + light.position.tobytes()
            for light in lights
        )
        lit_reused = reused and self._lit_prims is not None and self._lit_prims[0] == light_key
        if lit_reused and self._lit_prims is not None:
            beauty = self._lit_prims[1].copy()  # nothing moved and the lights did not change
        else:
            beauty = (
                shade(prims.albedo, prims.normal, prims.depth, prims.mask, camera, lights)
                if lights
                else prims.albedo.copy()
            )
            self._lit_prims = (light_key, beauty.copy())
        report["scene_prims"]["lit_reused"] = lit_reused
        timings["lighting"] += clock.perf_counter() - t
        albedo, normal = prims.albedo.copy(), prims.normal.copy()
        depth, mask = prims.depth.copy(), prims.mask.copy()
        visible: list[tuple[NeuralCharacter, dict, Any]] = []
        pending: dict[
            tuple[int, int], list[tuple[NeuralCharacter, Any, Any, np.ndarray, bytes]]
        ] = {}
        for character in self.characters:
            entry: dict[str, Any] = {"path": character.path}
            report["characters"].append(entry)
            if self.reference:
                entry.update(decision="reference", reason="the skinned mesh, drawn by the renderer")
                continue
            t = clock.perf_counter()
            try:
                world = character.pose(time)
            except SceneError as exc:
                # One bad frame of animation must not end a sequence, nor draw a wrong image:
                # the character is left out of this frame, loudly.
                entry.update(decision="skipped", reason=exc.what)
                print(f"rigspace render: warning: {exc}", file=sys.stderr)
                continue
            billboard = character.place(world, camera)
            if not billboard.visible:
                timings["rig"] += clock.perf_counter() - t
                entry.update(decision="skipped", reason=billboard.reason)
                continue
            rig = character.parameters(world, billboard, camera)
            timings["rig"] += clock.perf_counter() - t
            key = hashlib.sha1(
                rig.tobytes() + billboard.corners.tobytes() + _camera_key(camera)
            ).digest()
            cached = self._layers.get(character.path)
            if cached is not None and cached.key == key:
                entry.update(decision="reused", reason="same pose and camera as the last frame")
                visible.append((character, entry, billboard))
                continue
            level = character.model.level_for(billboard.size_px)
            pending.setdefault((id(character.model), level), []).append(
                (character, entry, billboard, rig, key)
            )
            visible.append((character, entry, billboard))
        # One network call per (model, level): characters sharing a bundle run as one batch.
        t = clock.perf_counter()
        for (_, level), group in pending.items():
            model = group[0][0].model
            out = model.predict(np.concatenate([g[3] for g in group]), level)
            for k, (character, entry, billboard, _rig, key) in enumerate(group):
                mine = {name: value[k : k + 1] for name, value in out.items()}
                layer = character.resample(mine, billboard, camera, level, ("albedo", "geometry"))
                self._layers[character.path] = _CachedLayer(key, layer)
                entry.update(decision="evaluated", batch=len(group))
        timings["network"] += clock.perf_counter() - t
        for character, entry, billboard in visible:
            cached = self._layers[character.path]
            layer = cached.layer
            entry.update(
                level=layer.level,
                branches=list(layer.branches),
                size_px=round(billboard.size_px, 1),
                region=[int(layer.x0), int(layer.y0), *map(int, layer.mask.shape[::-1])],
            )
            t = clock.perf_counter()
            if cached.lit is None or cached.lit_key != light_key:
                cached.lit_key = light_key
                cached.lit = (
                    shade(
                        layer.albedo,
                        layer.normal,
                        layer.depth,
                        layer.mask,
                        camera,
                        lights,
                        origin=(layer.x0, layer.y0),
                    )
                    if lights
                    else layer.albedo
                )
            timings["lighting"] += clock.perf_counter() - t
            t = clock.perf_counter()
            _composite(layer, cached.lit, beauty, albedo, normal, depth, mask)
            timings["composite"] += clock.perf_counter() - t
        report["seconds"] = {k: round(v, 6) for k, v in timings.items()}
        report["seconds"]["total"] = round(clock.perf_counter() - start, 6)
        return Frame(beauty, Maps(albedo, normal, depth, mask), report)


def _camera_key(camera: Camera) -> bytes:
    """Everything about a camera that changes what it sees."""
    lens = (
        camera.width,
        camera.height,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.near,
        camera.far,
    )
    return camera.camera_to_world.tobytes() + np.asarray(lens, dtype=np.float64).tobytes()


def _composite(layer: Layer, lit: np.ndarray, beauty, albedo, normal, depth, mask) -> None:
    """Depth-test a character layer against the frame and composite it with its coverage."""
    h, w = layer.mask.shape
    region = np.s_[layer.y0 : layer.y0 + h, layer.x0 : layer.x0 + w]
    char_depth = layer.depth
    scene_depth = depth[region]
    front = char_depth < scene_depth  # inf where empty loses every test
    a = np.where(front, layer.mask, 0.0)[..., None].astype(np.float32)
    beauty[region] = np.where(front[..., None], lit + (1 - a) * beauty[region], beauty[region])
    albedo[region] = np.where(
        front[..., None], layer.albedo + (1 - a) * albedo[region], albedo[region]
    )
    solid = front & (layer.mask >= 0.5)
    normal[region] = np.where(solid[..., None], layer.normal, normal[region])
    depth[region] = np.where(solid, char_depth, scene_depth)
    mask[region] = np.where(front, layer.mask + (1 - layer.mask) * mask[region], mask[region])

"""The runtime engine: a USD stage's frame with its neural characters drawn by their networks.

    engine = Engine("samples/scenes/previs.usda", EngineSettings(width=640, height=360))
    frame = engine.render(120.0)        # named images plus a report of what it computed

Per frame: the camera at t; the scene's other prims drawn by the renderer plugin into a
G-buffer (reused while neither they nor the camera move); per neural character the pose,
its billboard, and (when visible) its network maps in the billboard's region, reused when
pose and camera repeat, with its regions' maps (the face, a hand: bundles of their own,
where they add detail) merged in by depth (runtime/regions.py); each layer lit by the
scene's lights (runtime/lighting.py: shading.py's maths, compiled in shading_kernel.py, or
in a fragment shader on a GPU: gl_shading.py) and shadowed (runtime/shadows/frame.py: prims
by shadow maps, characters by their capsules, onto each other); then a depth test
composites the character over or under the prims, with its coverage as alpha at its edges
(composite_kernel.py), and a DomeLight fills what nothing covers. In the reference mode
each character's skinned mesh stands in for its network's maps, and for nothing else.
Every decision and every stage's time goes into the frame's report (FrameReport). A stage
without lights renders unlit (beauty = albedo) and unshadowed. Imports no torch.

The Engine decides what runs and when (`render`); how is in the strategies it chooses once
from its EngineSettings (runtime/settings.py): its Lighting and its FrameShadows, and in the
stages it hands what they need (runtime/stages: characters, prims, composite).
"""

from __future__ import annotations

import sys
import time as clock
from pathlib import Path

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom

from rigspace.runtime.character import NeuralCharacter
from rigspace.runtime.frame import STAGES, Frame, FrameCaches, FrameReport, FrameState, counts
from rigspace.runtime.lighting import choose_lighting
from rigspace.runtime.lights import Light, light_prims, lights_at
from rigspace.runtime.live.engine import LiveInput
from rigspace.runtime.scene import SceneGeometry
from rigspace.runtime.settings import AOVS, EngineSettings
from rigspace.runtime.shadows import ShadowBackend
from rigspace.runtime.shadows.frame import FrameShadows
from rigspace.runtime.stages.characters import CharacterStages
from rigspace.runtime.stages.composite import CompositeStage
from rigspace.runtime.stages.prims import Prims, PrimStages
from rigspace.sdk import schema, validation
from rigspace.sdk.camera import Camera
from rigspace.sdk.errors import SceneError
from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import RenderSettings, choose_renderer
from rigspace.sdk.render.gl import SharedContext
from rigspace.sdk.stage import might_vary, open_stage

__all__ = ["AOVS", "STAGES", "Engine", "EngineSettings", "Frame", "FrameReport", "use_models"]


class Engine:
    """Opens a stage, loads its neural characters' bundles, renders frames for one camera."""

    def __init__(self, scene: str | Path, settings: EngineSettings | None = None) -> None:
        """`settings` (EngineSettings: the camera, the size, the renderer, ...; None: the
        defaults) are chosen once. A scene that cannot be rendered is a SceneError naming why."""
        self.settings = settings = settings or EngineSettings()
        self.stage: Usd.Stage = open_stage(scene)
        validation.require_readable(self.stage, "render")  # before the camera and characters
        if settings.models:
            use_models(self.stage, settings.models)
        self.camera_prim = self._camera(settings.camera)
        validation.require_valid(self.stage, "render")  # inspect's checks, in inspect's words
        self.region_warnings: list[str] = []
        """One sentence per region left out at load (its bundle cannot be used), said once."""
        self.characters, self.without_model = self._load_characters()
        self.weight_overrides: dict[str, dict[str, float]] = {}
        """character path -> blend shape name -> weight that replaces the animation's (and a
        live source's) in every frame: `rigspace view`'s sliders (`set_weights`)."""
        live = settings.live and not settings.reference
        self.live = LiveInput(self.stage, self.characters, dict(settings.sources), live)
        """The characters' live bindings (runtime/live/engine.py)."""
        self.scene = SceneGeometry(self.stage)
        self.light_prims = light_prims(self.stage)
        spec = choose_renderer(settings.renderer)
        self._gl = SharedContext() if spec.name == "gl" else None
        """One EGL context for the renderers, the lighting and the capsule shadows."""
        if self._gl is not None:
            self._gl.acquire()  # held until close: its users come and go
        self.renderer = spec.create(RenderSettings(settings.prim_samples, shared=self._gl))
        self.caches = FrameCaches()
        self.shadows = FrameShadows(spec, settings.shadow_backend, self._gl)
        """The frame's shadows (runtime/shadows/frame.py); `shadows.record` keeps a frame's
        shadow passes to run again (the shadow timing tool)."""
        self.lighting = choose_lighting(
            spec, settings.gl_lighting, settings.lighting_kernel, self._gl
        )
        """What lights the prims and the characters' layers (runtime/lighting.py)."""
        self.overlap = True
        """Light the prims while the networks run (False: one after the other, the same
        images; 256x256 previs frame on 2 cores: 26.1 -> 23.5 ms, 512x512: 54 -> 49 ms)."""
        self.report_cpu = False
        """Also report each stage's CPU seconds (FrameReport.cpu_seconds, beside `seconds`):
        the process's, all threads, while the stage ran (a profiling aid: the shadow timing
        tool, `python -m rigspace.apps.shadow_timing`)."""
        self.character_stages = CharacterStages(
            self.characters, self.live, settings, spec, self.caches, self.weight_overrides, self._gl
        )
        self.prim_stages = PrimStages(self.renderer, self.shadows, self.lighting, self.caches)
        self.composite = CompositeStage(self.shadows, self.lighting, self.caches)
        self._no_shadow = [(c.path, c.no_shadow) for c in self.characters if c.no_shadow]
        self._light_problems: list[str] = []
        self._edited = False
        self._warn_characters()
        # Edits to the stage (a live session, a script) invalidate what was read as still.
        self._listener = Tf.Notice.Register(Usd.Notice.ObjectsChanged, self._changed, self.stage)

    def _load_characters(self) -> tuple[list[NeuralCharacter], list[str]]:
        """The stage's neural characters with their bundles (and their regions' bundles)
        loaded, and the paths of those without a model bundle."""
        precision, predictor = self.settings.precision, self.settings.predictor
        reference, textures = self.settings.reference, self.settings.textures
        characters: list[NeuralCharacter] = []
        without_model: list[str] = []
        loaded: dict[Path, BundleModel] = {}

        def open_model(folder: Path) -> BundleModel:
            folder = folder.resolve()
            if folder not in loaded:  # characters sharing a bundle share its sessions
                model = BundleModel(folder, precision, predictor=predictor)
                if not reference:
                    model.preload()  # a damaged bundle fails here, not mid-sequence
                loaded[folder] = model
            return loaded[folder]

        for prim in schema.neural_characters(self.stage):
            manifest = schema.resolve_model_path(schema.read_neural_character(prim))
            if manifest is None:
                without_model.append(str(prim.GetPath()))
                continue
            character = NeuralCharacter(prim, open_model(manifest.parent))
            if reference:  # the skinned mesh stands in for the body and its regions
                pass
            elif self.settings.regions:
                self.region_warnings += character.load_regions(open_model)
            else:
                character.region_problems = dict.fromkeys(
                    character.region_names, "regions are turned off (--no-regions)"
                )
            for part in (character, *character.regions):
                if not textures and part.textures is not None:
                    part.textures = None
                    part.no_texture = "textures are turned off (--no-textures)"
            characters.append(character)
        return characters, without_model

    def _warn_characters(self) -> None:
        """Warn once, at the start, of characters that cast no shadow, sample no texture, or
        whose training views (views.npy) cannot be read."""
        textured = self.settings.textures and not self.settings.reference
        for path, why in self._no_shadow:  # said once, here and in the first frame's report
            print(f"rigspace render: warning: {path} casts no shadow: {why}.", file=sys.stderr)
        for c in self.characters:
            for part in (c, *c.regions):
                which = c.path if part is c else f"{c.path} (region {part.name})"
                if part.model.charts and part.no_texture and textured:
                    print(
                        f"rigspace render: warning: {which} samples no texture, its colour comes "
                        f"from the albedo branch: {part.no_texture}.",
                        file=sys.stderr,
                    )
                if part.model.manifest.views is not None and part.views is None:
                    print(
                        f"rigspace render: warning: {which} reports no views its network never "
                        f"learned: {part.no_views}",
                        file=sys.stderr,
                    )
        for warning in self.region_warnings:
            print(f"rigspace render: warning: {warning}", file=sys.stderr)

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

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open_live(self) -> None:
        """Start the live bindings' sources now (else at the first frame): a source that
        cannot open raises one LiveSourceError naming the binding and the fix."""
        self.live.open()

    def close(self) -> None:
        self.live.close()
        self._listener.Revoke()
        self.character_stages.close()
        self.renderer.close()
        self.shadows.close()
        self.lighting.close()
        if self._gl is not None:
            self._gl.release()
            self._gl = None

    def use_shadow_backend(self, backend: ShadowBackend) -> None:
        """Compute the shadows with `backend` from the next call on (the shadow maps drawn so
        far are kept: the shadow bench times both kernels on the same inputs)."""
        self.shadows.use(backend)

    def render(self, time: float) -> Frame:
        """The frame at stage time `time`. Its arrays may be shared with later frames that
        change nothing (the frame cache): they are read-only; copy them to edit.

        The stages, in order: the camera and the lights (`_scene_stage`); the characters'
        poses and billboards (CharacterStages.pose); their network calls sent to the network
        thread, which also resamples their maps (.evaluate); the prims' G-buffer and shadow
        maps (PrimStages.draw), drawn meanwhile unless a character's branches depend on the
        prims' coverage (drawn before, then); the prims lit and shadowed (.light), meanwhile
        too; the networks' layers (CharacterStages.finish); the characters' lighting and the
        composite (CompositeStage). Each stage's time goes into the report's seconds."""
        start = clock.perf_counter()
        self.live.open()
        caches = self.caches
        if caches.frame is not None and caches.frame_at == time and not self.live.active:
            # The same time code and no edit to the stage since (the listener clears .frame):
            # every value read at this time is the same, so is the frame (a viewer redrawing).
            last = caches.frame[1]
            return Frame(last.beauty, last.maps, last.report.repeated(start), last.opaque)
        self._refresh_if_edited()
        f = self._scene_stage(time, start)
        characters = self.character_stages
        characters.pose(f)
        prims: Prims | None = None
        if characters.needs_coverage(f):  # an unlit decision reads the prims behind it
            prims = self.prim_stages.draw(f, self.scene)
        characters.evaluate(f, None if prims is None else prims.maps.mask)
        if prims is None:  # drawn while the networks run
            prims = self.prim_stages.draw(f, self.scene)
        beauty = None
        if f.pending and self.overlap:  # the prims lit while the networks run (a new frame)
            beauty = self.prim_stages.light(f, prims)
        characters.finish(f)
        self._summarise(f)
        # Nothing changed since the last frame: the same prims, lights, shadows and layers.
        frame_key = (
            caches.prims_key,
            f.light_key,
            self.shadows.key,
            tuple((path, posed.key) for path, posed in f.casters),
            tuple((c.key, caches.drawn[c.key].serial) for c in f.candidates),
        )
        if beauty is None and caches.frame is not None and caches.frame[0] == frame_key:
            return self._reused_composite(f)
        if beauty is None:
            beauty = self.prim_stages.light(f, prims)
        frame = self.composite(f, prims, beauty)
        f.report.shadows["maps_drawn"] = self.shadows.drawn  # drawn when first needed
        caches.frame, caches.frame_at = (frame_key, frame), time
        f.finish_report()
        return frame

    def _scene_stage(self, time: float, start: float) -> FrameState:
        """The frame's context: the camera, the lights and the report's start. The prims'
        meshes and G-buffer come later (PrimStages.draw), while the networks run."""
        camera, camera_key = self._camera_at(time)
        seconds = clock.perf_counter() - start
        lights = self._lights_at(time)
        report = FrameReport(
            time, str(self.camera_prim.GetPath()), len(lights), self.lighting.name,
            lights_left_out=self._light_problems or None,
        )  # fmt: skip
        report.characters += [
            {"path": p, "decision": "skipped", "reason": "no model bundle (rigspace:model)"}
            for p in self.without_model
        ]
        f = FrameState(time, start, camera, camera_key, lights, _light_key(lights), report,
                       cpu=self.report_cpu)  # fmt: skip
        f.timings["scene"] = seconds
        return f

    def _summarise(self, f: FrameState) -> None:
        """The report's summary once the characters' layers are known: counts, live
        bindings, shadows."""
        for entry in f.report.characters:  # the regions last in their character's entry
            if "regions" in entry:
                entry["regions"] = entry.pop("regions")
        f.report.counts = counts(f.report.characters)
        if self.live.active:
            f.report.live = self.live.report()
        f.report.shadows = {"maps_drawn": self.shadows.drawn, "casters": len(f.casters)}
        if self._no_shadow:  # said once
            f.report.shadows["without_capsules"] = [p for p, _ in self._no_shadow]
            self._no_shadow = []

    def _reused_composite(self, f: FrameState) -> Frame:
        """The last frame's images with this frame's report: nothing it shows has changed."""
        assert self.caches.frame is not None
        last = self.caches.frame[1]
        f.report.composite_reused = True
        f.report.scene_prims["lit_reused"] = True
        f.report.background = last.report.background
        f.finish_report()
        self.caches.frame_at = f.time
        return Frame(last.beauty, last.maps, f.report, last.opaque)

    def _refresh_if_edited(self) -> None:
        if self._edited:
            self._edited = False
            self.scene = SceneGeometry(self.stage)
            self.light_prims = light_prims(self.stage)
            # The G-buffer is keyed on its meshes' identities, which new meshes may reuse.
            self.caches.prims, self.caches.lit_prims = None, None

    def _changed(self, notice, sender) -> None:
        """The stage was edited: nothing read from it so far can be trusted to be still."""
        self.caches.stage_edited()
        self._edited = True  # prims and lights are found again before the next frame

    def _camera_at(self, time: float) -> tuple[Camera, bytes]:
        caches = self.caches
        if caches.still_camera is not None:
            return caches.still_camera
        width, height = self.settings.width, self.settings.height
        camera = Camera.from_usd(self.camera_prim, time, width, height)
        key = _camera_key(camera)
        if caches.camera_varies is None:
            caches.camera_varies = might_vary(self.camera_prim)
        if not caches.camera_varies:  # the same at every time: read it once
            caches.still_camera = (camera, key)
        return camera, key

    def _lights_at(self, time: float) -> list[Light]:
        if "beauty" not in self.settings.aovs:
            return []  # without a beauty AOV nothing is shaded
        caches = self.caches
        if caches.still_lights is not None:
            lights, self._light_problems = caches.still_lights
            return lights
        self._light_problems = []
        lights = lights_at(self.light_prims, time, self._light_problem)
        if caches.lights_vary is None:
            caches.lights_vary = any(might_vary(p) for p in self.light_prims)
        if not caches.lights_vary:  # still lights: read once, their problems reported each frame
            caches.still_lights = (lights, self._light_problems)
        return lights

    def _light_problem(self, problem: SceneError) -> None:
        """Called by lights_at for a light it leaves out of this frame."""
        print(f"rigspace render: warning: {problem} The light is left out.", file=sys.stderr)
        self._light_problems.append(problem.what)

    def coverage_of(self, path: str, time: float) -> np.ndarray | None:
        """(H, W) a character's own coverage at `time`, before any depth test: its layer's in
        the last frame, rendered at `time` (None when it was not drawn); in the reference mode
        its skinned mesh's, drawn alone (what `--reference` measures the network's silhouette
        against)."""
        character = next((c for c in self.characters if c.path == path), None)
        if character is None:
            return None
        camera, _ = self._camera_at(time)
        cached = self.caches.drawn.get(path)
        if cached is None:
            return None
        layer = cached.layer
        full = np.zeros((camera.height, camera.width), np.float32)
        h, w = layer.mask.shape
        full[layer.y0 : layer.y0 + h, layer.x0 : layer.x0 + w] = layer.mask
        return full

    def set_weights(self, path: str, weights: dict[str, float]) -> None:
        """Override blend shape weights or controls (RigspaceControlAPI) of the character at
        `path` from the next frame on (an empty dict clears them). A name the character lacks,
        or a weight that is not a finite number, is a ValueError naming it."""
        character = next((c for c in self.characters if c.path == path), None)
        if character is None:
            raise ValueError(f"{path} is not a neural character of this stage")
        for name, value in weights.items():
            if name not in character.rig.scalar_names:
                raise ValueError(f"{path} has no blend shape or control {name!r}")
            if not isinstance(value, int | float) or not np.isfinite(value):
                raise ValueError(f"the weight of {name!r} must be a finite number")
        before = self.weight_overrides.get(path)
        if weights:
            self.weight_overrides[path] = {k: float(v) for k, v in weights.items()}
        else:
            self.weight_overrides.pop(path, None)
        if self.weight_overrides.get(path) != before:
            self.caches.frame_at = None  # the same time code is not the same frame any more


def use_models(stage: Usd.Stage, models: dict[str, str]) -> None:
    """Author each character's rigspace:model in the stage's session layer (render --model):
    "" names the stage's only neural character. A path that is not a neural character, or ""
    on a stage with several, is a SceneError naming them."""
    characters = [str(p.GetPath()) for p in schema.neural_characters(stage)]
    for path, bundle in models.items():
        if not path:
            if len(characters) != 1:
                raise SceneError(
                    f"--model {bundle}: the stage has {len(characters)} neural characters "
                    f"({', '.join(characters) or 'none'}).",
                    "name the one it is for: --model /World/Hero=BUNDLE.",
                )
            path = characters[0]
        if path not in characters:
            raise SceneError(
                f"--model {path}={bundle}: {path} is not a neural character of the stage.",
                f"use one of: {', '.join(characters) or '(none)'}.",
            )
        folder = Path(bundle).resolve()
        if not (folder / "manifest.json").is_file():
            raise SceneError(
                f"--model {bundle} is not a model bundle (no manifest.json there).",
                "give the folder `rigspace train ... --out` wrote.",
            )
        with Usd.EditContext(stage, stage.GetSessionLayer()):
            attr = stage.GetPrimAtPath(path).GetAttribute("rigspace:model")
            if not attr:
                attr = stage.GetPrimAtPath(path).CreateAttribute(
                    "rigspace:model", Sdf.ValueTypeNames.Asset, custom=False
                )
            attr.Set(Sdf.AssetPath(str(folder)))


def _light_key(lights: list[Light]) -> bytes:
    """Everything about the lights that changes how they light."""
    return b"".join(
        light.radiance.tobytes()
        + light.direction.tobytes()
        + light.position.tobytes()
        + np.array([light.angle, light.radius]).tobytes()
        + light.orientation.tobytes()
        for light in lights
    )


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

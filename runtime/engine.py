"""The runtime engine: a USD stage's frame with its neural characters drawn by their networks.

    engine = Engine("samples/scenes/previs.usda", width=640, height=360)
    frame = engine.render(120.0)        # named images plus a report of what it computed

Per frame: the camera at t; the scene's other prims drawn by the renderer plugin into a
G-buffer (reused while neither they nor the camera move); per neural character the pose,
its billboard, and (when visible) its network maps in the billboard's region, reused when
pose and camera repeat, with its regions' maps (the face, a hand: bundles of their own,
where they add detail) merged in by depth (runtime/regions.py); each layer lit by the scene's lights (runtime/shading.py's maths,
compiled in shading_kernel.py, or in a fragment shader on a GPU: gl_shading.py) and
shadowed (runtime/shadows/__init__.py: prims by shadow maps, characters by their capsules, onto
each other); then a depth test composites the character over or under the prims, with its
coverage as alpha at its edges (composite_kernel.py), and a DomeLight fills what nothing
covers. In the reference mode each character's skinned mesh stands in for its network's
maps, and for nothing else. Every decision and every stage's time goes into the frame's
report. A stage without lights renders unlit (beauty = albedo) and unshadowed. Imports no
torch.
"""

from __future__ import annotations

import itertools
import sys
import time as clock
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom

from rigspace.runtime.billboard import Billboard
from rigspace.runtime.character import Layer, NeuralCharacter, NeuralPart
from rigspace.runtime.composite_kernel import composite, over_background
from rigspace.runtime.gl_shading import GLShading, open_gl_shading
from rigspace.runtime.lights import (
    AMBIENT,
    DISTANT,
    POINT,
    Light,
    background,
    light_prims,
    lights_at,
)
from rigspace.runtime.live.engine import LiveInput
from rigspace.runtime.regions import merge_region, region_skip
from rigspace.runtime.scene import SceneGeometry
from rigspace.runtime.shading import pixel_positions, shade_pixels
from rigspace.runtime.shading_kernel import shade as compiled_shade
from rigspace.runtime.shadows import (
    CompiledPasses,
    PosedCapsules,
    PrimShadows,
    ShadowBackend,
    region_mask,
    shadow_regions,
    sparse_visibility,
)
from rigspace.runtime.shadows import passes as shadow_pass
from rigspace.sdk import schema, validation
from rigspace.sdk.camera import Camera
from rigspace.sdk.errors import SceneError
from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import Maps, RenderSettings, choose_renderer, empty_maps
from rigspace.sdk.stage import might_vary, open_stage

STAGES = ("scene", "rig", "network", "shadows", "lighting", "composite")
AOVS = ("beauty", "albedo", "normal", "depth", "mask")
"""The images a frame can give (Frame.beauty and Frame.maps)."""
BOTH = ("albedo", "geometry")


@dataclass
class Frame:
    """One rendered frame: premultiplied beauty and the composited maps, plus its report."""

    beauty: np.ndarray
    """(H, W, 3) lit colour, premultiplied by `mask`; over the background where there is one."""
    maps: Maps
    report: dict[str, Any] = field(default_factory=dict)
    opaque: bool = False
    """A background (a DomeLight) fills the pixels nothing covers: the beauty's alpha is 1."""

    @property
    def alpha(self) -> np.ndarray:
        """(H, W) the beauty's alpha: 1 over a background, else the coverage (maps.mask)."""
        return np.ones_like(self.maps.mask) if self.opaque else self.maps.mask


POSE_TOLERANCE = 1e-5
"""Joint rotations (matrix entries) and translations (in billboard sides) closer than this
to the cached pose count as the same pose: a hold interpolated at fractional times differs
by rounding only (3e-5 measured), far below a pixel at any level (1e-5 of 128 pixels)."""

_serials = itertools.count()


@dataclass
class _CachedLayer:
    pose: np.ndarray
    """(J, 4, 4) the model's joints' world transforms the layer was evaluated for."""
    view: bytes
    """The camera and billboard corners it was evaluated for (exact)."""
    layer: Layer
    lit: np.ndarray | None = None
    lit_key: bytes = b""
    """The lights `lit` was shaded with: lights that change re-light a reused layer."""
    serial: int = field(default_factory=lambda: next(_serials))
    """Identifies this evaluation in the frame cache's key."""

    weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    """(B,) the blend shape weights it was evaluated for (model order)."""

    def matches(self, pose: np.ndarray, view: bytes, side: float, weights: np.ndarray) -> bool:
        if view != self.view:
            return False
        if len(weights) and np.abs(weights - self.weights).max() >= POSE_TOLERANCE:
            return False
        rotation = np.abs(pose[:, :3, :3] - self.pose[:, :3, :3]).max()
        translation = np.abs(pose[:, :3, 3] - self.pose[:, :3, 3]).max() / side
        return bool(rotation < POSE_TOLERANCE and translation < POSE_TOLERANCE)


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
        aovs: tuple[str, ...] = AOVS,
        prim_samples: int = 2,
        max_level: int | None = None,
        textures: bool = True,
        live: bool = True,
        sources: dict[str, str] | None = None,
        predictor: str = "auto",
        models: dict[str, str] | None = None,
        shadow_backend: ShadowBackend | None = None,
        gl_lighting: str = "hardware",
        regions: bool = True,
    ) -> None:
        """`reference=True` draws each character's real skinned mesh with the renderer instead
        of its network (the ground truth that `rigspace render --reference` compares with).
        `aovs` are the images the caller will read: without `normal` and `depth`, a character
        with no lights on it and nothing overlapping its billboard runs its albedo branch only.
        `prim_samples` per axis anti-alias the scene prims (2: 2x2 per pixel; 1: none, about
        twice as fast on a software renderer). `max_level` caps the level of detail (the
        network's output resolution) to trade detail for time. `textures` False colours every
        character from its albedo branch even where its bundle has a texture head (a
        comparison, or a scene whose textures should not be read). `live`: enabled
        RigspaceLiveBindingAPI bindings drive their characters (runtime/live; their sources
        open at the first frame, or `open_live()`; `close()` or `with` stops them);
        `sources` maps binding names to URLs that replace theirs and enable them. `predictor`
        runs the networks (rigspace.sdk.predictors; "auto": the fastest that can). `models`
        maps neural character paths ("" for the stage's only one) to model bundles drawn
        instead of their rigspace:model, in the session layer: the scene file is not edited.
        `shadow_backend` says what computes the shadows (rigspace.runtime.shadows.ShadowBackend:
        the compiled kernels and, on a GPU, the fragment shader by default). `gl_lighting`
        says where the lighting runs in a fragment shader (runtime/gl_shading.py:
        "hardware", the gl renderer on a GPU; "always", on Mesa's llvmpipe too; "never").
        `regions` False draws each character's body alone, never its regions (the face, a
        hand: bundles of their own listed in its manifest, docs/regions.md; not loaded)."""
        _check_request(aovs, width, height)
        self.aovs = tuple(aovs)
        self.max_level = max_level
        self.stage: Usd.Stage = open_stage(scene)
        validation.require_readable(self.stage, "render")  # before the camera and characters
        if models:
            use_models(self.stage, models)
        self.width, self.height = width, height
        self.camera_prim = self._camera(camera)
        validation.require_valid(self.stage, "render")  # inspect's checks, in inspect's words
        self.region_warnings: list[str] = []
        """One sentence per region left out at load (its bundle cannot be used), said once."""
        self.characters, self.without_model = self._load_characters(
            precision, predictor, reference, textures, regions
        )
        self.reference = reference
        self.weight_overrides: dict[str, dict[str, float]] = {}
        """character path -> blend shape name -> weight that replaces the animation's (and a
        live source's) in every frame: `rigspace view`'s sliders (`set_weights`)."""
        self.live = LiveInput(self.stage, self.characters, sources or {}, live and not reference)
        """The characters' live bindings (runtime/live/engine.py)."""
        self.scene = SceneGeometry(self.stage)
        self.light_prims = light_prims(self.stage)
        spec = choose_renderer(renderer)
        self.renderer = spec.create(RenderSettings(prim_samples))
        self._spec, self._prim_samples = spec, prim_samples
        self._mesh_renderer: Any = None
        """The reference mode's renderer of the characters' meshes (their own: the prims'
        keeps its uploads while they are drawn apart)."""
        self._init_caches()
        self.shadows = PrimShadows(spec)
        self._network = ThreadPoolExecutor(max_workers=1, thread_name_prefix="rigspace-network")
        """Runs the frame's network calls while the frame's thread draws and lights the prims."""
        self.overlap = True
        """Light the prims while the networks run (False: one after the other, the same
        images; 256x256 previs frame on 2 cores: 26.1 -> 23.5 ms, 512x512: 54 -> 49 ms)."""
        self.report_cpu = False
        """Also report each stage's CPU seconds (`report["cpu_seconds"]`, beside `seconds`):
        the process's, all threads, while the stage ran (a profiling aid: the shadow timing
        tool, `python -m rigspace.apps.shadow_timing`)."""
        self.shadow_passes: dict[str, Callable[[], Any]] | None = None
        """None, or a dict that each frame fills with its shadow passes, each a call that runs
        the pass again on the same inputs with the shadow backend in use then: "prims" (the
        prims' shadows from the maps and the capsules) and "layer" (a character layer's, the
        frame's last). The shadow timing tool repeats them."""
        self.gl_shading: GLShading | None = open_gl_shading(spec, gl_lighting)
        """The fragment shader that lights the prims and the characters' layers; None: numpy."""
        self._compiled: CompiledPasses | None = None
        """The kernels' passes when the backend computes with numba, else None (numpy)."""
        self.use_shadow_backend(shadow_backend or ShadowBackend())
        self._no_shadow = [(c.path, c.no_shadow) for c in self.characters if c.no_shadow]
        self._warn_characters(textures)
        # Edits to the stage (a live session, a script) invalidate what was read as still.
        self._listener = Tf.Notice.Register(Usd.Notice.ObjectsChanged, self._changed, self.stage)

    def _load_characters(
        self, precision: str, predictor: str, reference: bool, textures: bool, regions: bool
    ) -> tuple[list[NeuralCharacter], list[str]]:
        """The stage's neural characters with their bundles (and their regions' bundles)
        loaded, and the paths of those without a model bundle."""
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
            elif regions:
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

    def _init_caches(self) -> None:
        """The caches kept between frames, empty: G-buffer, layers, lighting, last frame."""
        self._prims_key: tuple = ()
        self._prims: Maps | None = None
        self._layers: dict[str, _CachedLayer] = {}
        """Each body's and region's last evaluated layer, by _Candidate.key."""
        self._drawn: dict[str, _CachedLayer] = {}
        """Each character's layer as the last frame lit and composited it: its body's, or its
        body's with its regions merged in (kept in `_merges` while they hold)."""
        self._merges: dict[str, tuple[tuple[int, ...], _CachedLayer]] = {}
        """A character's merged layer, keyed by the serials of the layers merged."""
        self._lit_prims: tuple[bytes, np.ndarray | None, list[np.ndarray | None] | None] | None = (
            None
        )
        """The lit prims, keyed by lights and shadow maps, with each light's shadow factor."""
        self._box: tuple[tuple, np.ndarray] | None = None
        self._background: tuple[bytes, np.ndarray] | None = None
        self._frame: tuple[tuple, Frame] | None = None
        self._light_problems: list[str] = []
        self._edited = False
        self._frame_at: float | None = None
        """The time code of the last frame (the frame cache answers it again at once)."""
        self._still_camera: tuple[Camera, bytes] | None = None
        self._still_lights: tuple[list[Light], list[str]] | None = None
        self._camera_varies: bool | None = None
        self._lights_vary: bool | None = None

    def _warn_characters(self, textures: bool) -> None:
        """Warn once, at the start, of characters that cast no shadow or sample no texture."""
        for path, why in self._no_shadow:  # said once, here and in the first frame's report
            print(f"rigspace render: warning: {path} casts no shadow: {why}.", file=sys.stderr)
        for c in self.characters:
            for part in (c, *c.regions):
                if part.model.charts and part.no_texture and not self.reference and textures:
                    which = c.path if part is c else f"{c.path} (region {part.name})"
                    print(
                        f"rigspace render: warning: {which} samples no texture, its colour comes "
                        f"from the albedo branch: {part.no_texture}.",
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
        self._network.shutdown(wait=True)
        self.renderer.close()
        if self._mesh_renderer is not None:
            self._mesh_renderer.close()
            self._mesh_renderer = None
        self.shadows.close()
        if self.gl_shading is not None:
            self.gl_shading.close()
            self.gl_shading = None

    def _scene_maps(self, meshes, camera: Camera, camera_key: bytes) -> tuple[Maps, bool]:
        key = (tuple(id(m) for m in meshes), camera_key)
        if self._prims is not None and key == self._prims_key:
            return self._prims, True
        maps = (
            self.renderer.render(meshes, camera)
            if meshes
            else empty_maps(camera.height, camera.width)
        )
        self._prims, self._prims_key = maps, key
        return maps, False

    def _branches(
        self,
        c: _Candidate,
        candidates: list[_Candidate],
        scene_mask: Callable[[], np.ndarray],
        lit: bool,
    ) -> tuple[tuple[str, ...], str]:
        """The map branches a character needs this frame, and why (the unlit mode's decision).
        `scene_mask` draws the prims' coverage when asked: only an unlit character asks."""
        if lit:
            return BOTH, "lights reach it: normals and depth are shaded"
        if c.character.textures is not None and c.character.model.texture_branch == "geometry":
            return BOTH, "its texture head is on the geometry branch"
        if {"normal", "depth"} & set(self.aovs):
            return BOTH, "the normal or depth AOV is asked for"
        if not c.character.model.albedo_has_alpha:
            return BOTH, "its bundle (format 1) takes coverage from the geometry branch"
        x0, y0, w, h = c.region
        if np.any(scene_mask()[y0 : y0 + h, x0 : x0 + w] > 0):
            return BOTH, "a scene prim overlaps its billboard: depth-tested"
        if any(_overlaps(c.region, o.region) for o in candidates if o is not c):
            return BOTH, "another character overlaps its billboard: depth-tested"
        return ("albedo",), "no lights and nothing overlapping its billboard"

    def _changed(self, notice, sender) -> None:
        """The stage was edited: nothing read from it so far can be trusted to be still."""
        self._still_camera = self._still_lights = None
        self._camera_varies = self._lights_vary = None
        self._frame = None
        self._edited = True  # prims and lights are found again before the next frame

    def _camera_at(self, time: float) -> tuple[Camera, bytes]:
        if self._still_camera is not None:
            return self._still_camera
        camera = Camera.from_usd(self.camera_prim, time, self.width, self.height)
        key = _camera_key(camera)
        if self._camera_varies is None:
            self._camera_varies = might_vary(self.camera_prim)
        if not self._camera_varies:  # the same at every time: read it once
            self._still_camera = (camera, key)
        return camera, key

    def _lights_at(self, time: float) -> list[Light]:
        if "beauty" not in self.aovs:
            return []  # without a beauty AOV nothing is shaded
        if self._still_lights is not None:
            lights, self._light_problems = self._still_lights
            return lights
        self._light_problems = []
        lights = lights_at(self.light_prims, time, self._light_problem)
        if self._lights_vary is None:
            self._lights_vary = any(might_vary(p) for p in self.light_prims)
        if not self._lights_vary:  # still lights: read once, their problems reported each frame
            self._still_lights = (lights, self._light_problems)
        return lights

    def _light_problem(self, problem: SceneError) -> None:
        """Called by lights_at for a light it leaves out of this frame."""
        print(f"rigspace render: warning: {problem} The light is left out.", file=sys.stderr)
        self._light_problems.append(problem.what)

    @staticmethod
    def _shadowing(lights: list[Light]) -> bool:
        """Whether any light casts shadows (the ambient one does not)."""
        return any(light.kind in (DISTANT, POINT) for light in lights)

    def _update_shadow_maps(self, meshes, lights: list[Light]) -> None:
        """The prims' shadow maps: still prims in one map per light, each moving one in its own.
        `meshes` are the scene's prims only: a character casts through its capsules (in the
        reference mode too, so that the two modes differ only in the character's maps)."""
        if not self._shadowing(lights):
            self.shadows.update([], [])
            return
        still = [m for m in meshes if id(m) not in self.scene.moving]
        moving = [(f"moving {m.name}", [m]) for m in meshes if id(m) in self.scene.moving]
        self.shadows.update(lights, [("still", still), *moving])

    def _scene_box(self, meshes) -> np.ndarray:
        """(2, 3) bounds of the prims (where a capsule shadow can land), cached with them."""
        key = tuple(id(m) for m in meshes)
        if self._box is None or self._box[0] != key:
            if meshes:
                lo = np.min([m.points.min(axis=0) for m in meshes], axis=0)
                hi = np.max([m.points.max(axis=0) for m in meshes], axis=0)
            else:
                lo = hi = np.zeros(3)
            self._box = (key, np.array([lo, hi], dtype=np.float64))
        return self._box[1]

    def _prim_shadows(
        self, prims: Maps, camera: Camera, lights: list[Light], meshes, casters, maps: bool
    ) -> tuple[list[np.ndarray | None], list[np.ndarray | None]]:
        """Per light, the prims' (H, W) shadow factor from the shadow maps (with `maps`) and
        from the characters' capsules (None: none can fall), each found coarse to fine
        (sparse_visibility) in the window of its own screen regions. (One pass for both, on
        the union of their windows, measured slower: the capsules' small window grew to the
        maps' and more pixels were evaluated.) The same passes run compiled in shadow_pass.py
        unless the capsules go to the fragment shader or the backend's kernel is "numpy"."""
        if self.shadow_passes is not None:
            self.shadow_passes["prims"] = partial(
                self._prim_shadows, prims, camera, lights, meshes, casters, maps
            )
        box = self._scene_box(meshes)
        if self._compiled is not None and self.shadows.capsule_backend == "numpy":
            return shadow_pass.prim_shadows(self.shadows, prims, camera, lights, box, casters, maps)
        bounds = [(posed, [part.bounds() for part in posed.parts()]) for _, posed in casters]
        jobs: list[tuple[int, int, list, Any]] = []  # (light, pass, regions, map or capsules)
        passes: dict[tuple[int, str], int] = {}  # a pass per light and kind
        for index, light in enumerate(lights):
            if light.kind not in (DISTANT, POINT):
                continue
            if maps:
                for rects, handle in self.shadows.regions(index, box, camera):
                    number = passes.setdefault((index, "map"), len(passes))
                    jobs.append((index, number, rects, handle))
            # Per caster, the regions its limbs' shadows can fall on (a limb's region is
            # much smaller than the whole body's).
            for posed, spheres in bounds:
                centres = np.array([c for c, _ in spheres])
                reach = np.array([r for _, r in spheres])[:, None]
                find = self._compiled.shadow_regions if self._compiled else shadow_regions
                rects = find(centres - reach, centres + reach, light, box, camera)
                rects = [r for r in rects if r is not None]
                if rects:
                    number = passes.setdefault((index, "capsules"), len(passes))
                    jobs.append((index, number, rects, posed))
        mapped: list[np.ndarray | None] = [None] * len(lights)
        hidden: list[np.ndarray | None] = [None] * len(lights)
        for (index, kind), number in passes.items():
            mine = [job for job in jobs if job[1] == number]
            window = _window([r for _, _, rects, _ in mine for r in rects])
            covered = prims.mask[window] > 0
            areas = [covered & region_mask(rects, camera, window) for _, _, rects, _ in mine]

            def evaluate(pixels: np.ndarray, mine=mine, areas=areas, window=window) -> np.ndarray:
                frame = _in_frame(pixels, window, camera)
                points, normals = self._prim_points(prims, camera, frame)
                v = np.ones(pixels.size, np.float32)
                for area, (index, _, _, what) in zip(areas, mine, strict=True):
                    inside = np.flatnonzero(area.reshape(-1)[pixels])
                    if isinstance(what, PosedCapsules):
                        seen = self.shadows.capsule_visibility(
                            points[:, inside], what, lights[index]
                        )
                    else:
                        seen = self.shadows.lookup(what, points[:, inside], normals[:, inside])
                    v[inside] *= seen
                return v

            full = np.ones((camera.height, camera.width), np.float32)
            candidates = np.logical_or.reduce(areas)
            full[window] = sparse_visibility(candidates, evaluate, prims.depth[window])
            (mapped if kind == "map" else hidden)[index] = full
        return mapped, hidden

    @staticmethod
    def _prim_points(prims: Maps, camera: Camera, pixels: np.ndarray):
        """Planar world positions and normals of flat pixel indices of the prims' G-buffer."""
        rows, cols = np.divmod(pixels, camera.width)
        return _world_points(
            prims.depth.reshape(-1)[pixels], rows, cols, prims.normal.reshape(-1, 3)[pixels],
            camera, (0, 0),
        )  # fmt: skip

    def _shade(self, albedo, normal, depth, mask, camera: Camera, lights, origin=(0, 0),
               visibility=None) -> np.ndarray:  # fmt: skip
        """shading.shade: in the fragment shader where the engine has one (gl_shading), else
        compiled (shading_kernel)."""
        light = compiled_shade if self.gl_shading is None else self.gl_shading.shade
        return light(albedo, normal, depth, mask, camera, lights, origin, visibility)

    def _shade_prims(self, prims: Maps, camera: Camera, lights, visibility) -> np.ndarray:
        """The prims' G-buffer lit, with per-light shadow factors `visibility`."""
        if not lights:
            return prims.albedo.copy()
        return self._shade(
            prims.albedo, prims.normal, prims.depth, prims.mask, camera, lights,
            visibility=visibility,
        )  # fmt: skip

    def _capsule_reshade(
        self, beauty, prims: Maps, camera: Camera, lights, hidden, shadowed
    ) -> None:
        """Re-shade, in `beauty` (the prims lit with the maps' shadows `shadowed`), the prim
        pixels the characters' capsules shadow (`hidden`, per light)."""
        dark = [v < 1.0 for v in hidden if v is not None]
        if not dark:
            return
        flat = np.flatnonzero(np.logical_or.reduce(dark))
        if flat.size == 0:
            return
        # Only the pixels a capsule shadows are shaded again, with every light's shadows.
        visibility: list[np.ndarray | None] = []
        for index, v in enumerate(hidden):
            seen = None if v is None else v.reshape(-1)[flat]
            factor = None if shadowed is None else shadowed[index]
            if factor is not None:
                mapped = factor.reshape(-1)[flat]
                seen = mapped if seen is None else seen * mapped
            visibility.append(seen)
        rows, cols = np.divmod(flat, camera.width)
        beauty.reshape(-1, 3)[flat] = shade_pixels(
            prims.albedo.reshape(-1, 3)[flat],
            prims.normal.reshape(-1, 3)[flat],
            pixel_positions(prims.depth.reshape(-1)[flat], rows, cols, camera),
            prims.mask.reshape(-1)[flat],
            camera.world_to_camera,
            lights,
            visibility,
        )

    def _layer_visibility(
        self, layer: Layer, camera: Camera, lights: list[Light], others, meshes
    ) -> list[np.ndarray | None] | None:
        """Per light, a character layer's (h, w) shadow factor: the prims' shadow maps and the
        other characters' capsules (its own capsules would shadow its own surface)."""
        if self.shadow_passes is not None:
            self.shadow_passes["layer"] = partial(
                self._layer_visibility, layer, camera, lights, others, meshes
            )
        if not self._shadowing(lights) or layer.depth is None or layer.normal is None:
            return None
        if self._compiled is not None and self.shadows.capsule_backend == "numpy":
            box = self._scene_box(meshes)
            return shadow_pass.layer_visibility(self.shadows, layer, camera, lights, box, others)
        h, w = layer.mask.shape
        covered = np.flatnonzero(layer.mask > 0)
        rows, cols = np.divmod(covered, w)
        points, normals = _world_points(
            layer.depth.reshape(-1)[covered], rows, cols, layer.normal.reshape(-1, 3)[covered],
            camera, (layer.x0, layer.y0),
        )  # fmt: skip
        box = self._scene_box(meshes)
        out: list[np.ndarray | None] = []
        for index, light in enumerate(lights):
            v = None
            for rects, handle in self.shadows.regions(index, box, camera):
                # Only the maps whose shadows can reach the layer's rectangle.
                if any(_overlaps(_rect(r), (layer.x0, layer.y0, w, h)) for r in rects):
                    seen = self.shadows.lookup(handle, points, normals)
                    v = seen if v is None else v * seen
            if light.kind in (DISTANT, POINT):
                for _, posed in others:
                    seen = self.shadows.capsule_visibility(points, posed, light)
                    v = seen if v is None else v * seen
            if v is None:
                out.append(None)
                continue
            full = np.ones(h * w, np.float32)
            full[covered] = v
            out.append(full.reshape(h, w))
        return out

    def _dome_background(self, dome: Light, camera: Camera, camera_key: bytes) -> np.ndarray:
        """What a DomeLight shows behind everything, cached while camera and dome are still."""
        key = camera_key + dome.radiance.tobytes() + dome.orientation.tobytes()
        key += b"" if dome.texture is None else np.int64(id(dome.texture)).tobytes()
        if self._background is None or self._background[0] != key:
            self._background = (key, background(dome, camera))
        return self._background[1]

    def render(self, time: float) -> Frame:
        """The frame at stage time `time`. Its arrays may be shared with later frames that
        change nothing (the frame cache): they are read-only; copy them to edit.

        The frame is a sequence of named stages over one per-frame context (`_FrameState`):
        the camera and the lights (`_scene_stage`), the characters' poses and billboards
        (`_pose_stage`), their network evaluations sent to the network thread, which also
        resamples their maps (`_evaluate_stage`), the prims' meshes, G-buffer and shadow maps
        (`_prims_stage`, drawn meanwhile), the prims' shadows and lighting
        (`_light_prims_stage`), the characters' lighting and compositing (`_composite_stage`).
        Each stage's time is added to the report's seconds by `timed`."""
        f = _FrameState(time, clock.perf_counter(), cpu=self.report_cpu)
        self.live.open()
        if self._frame is not None and self._frame_at == time and not self.live.active:
            # The same time code and no edit to the stage since (the listener clears _frame):
            # every value read at this time is the same, so is the frame (a viewer redrawing).
            return self._repeat(self._frame[1], f.start)
        self._refresh_if_edited()
        self._scene_stage(f)
        self._pose_stage(f)
        self._evaluate_stage(f)
        self._prims_stage(f)  # drawn while the networks run, unless a decision needed them
        beauty = None
        if f.pending and self.overlap:  # the prims lit while the networks run (a new frame)
            beauty = self._light_prims_stage(f)
        self._finish_evaluation(f)
        for entry in f.report["characters"]:  # the regions last in their character's entry
            if "regions" in entry:
                entry["regions"] = entry.pop("regions")
        f.report["counts"] = _counts(f.report["characters"])
        if self.live.active:
            f.report["live"] = self.live.report()
        f.report["shadows"]["casters"] = len(f.casters)
        # Nothing changed since the last frame: the same prims, lights, shadows and layers.
        frame_key = (
            self._prims_key,
            f.light_key,
            self.shadows.key,
            tuple((path, posed.key) for path, posed in f.casters),
            tuple((c.key, self._drawn[c.key].serial) for c in f.candidates),
        )
        if beauty is None and self._frame is not None and self._frame[0] == frame_key:
            return self._reused_composite(f)
        f.report["composite_reused"] = False
        if beauty is None:
            beauty = self._light_prims_stage(f)
        frame = self._composite_stage(f, beauty)
        self._frame = (frame_key, frame)
        self._frame_at = time
        f.report.update(f.seconds())
        return frame

    def _refresh_if_edited(self) -> None:
        if self._edited:
            self._edited = False
            self.scene = SceneGeometry(self.stage)
            self.light_prims = light_prims(self.stage)
            # The G-buffer is keyed on its meshes' identities, which new meshes may reuse.
            self._prims, self._lit_prims = None, None

    def _scene_stage(self, f: _FrameState) -> None:
        """The camera, the lights and the report's start. The prims' meshes and G-buffer
        come later (_prims_stage), while the networks run."""
        f.camera, f.camera_key = self._camera_at(f.time)
        f.timings["scene"] = clock.perf_counter() - f.start
        f.lights = lights = self._lights_at(f.time)
        f.report = {
            "time": f.time,
            "camera": str(self.camera_prim.GetPath()),
            "scene_prims": {},
            "lights": len(lights),
            "lighting_on": "numba" if self.gl_shading is None else self.gl_shading.renderer,
            "characters": [],
        }
        if self._light_problems:
            f.report["lights_left_out"] = self._light_problems
        f.report["characters"] += [
            {"path": p, "decision": "skipped", "reason": "no model bundle (rigspace:model)"}
            for p in self.without_model
        ]
        f.light_key = b"".join(
            light.radiance.tobytes()
            + light.direction.tobytes()
            + light.position.tobytes()
            + np.array([light.angle, light.radius]).tobytes()
            + light.orientation.tobytes()
            for light in lights
        )

    def _prims_stage(self, f: _FrameState) -> Maps:
        """The prims' meshes, their G-buffer (the last frame's while prims and camera hold)
        and the lights' shadow maps; once a frame, whichever stage asks first."""
        if f.prims is not None:
            return f.prims
        with f.timed("scene"):
            f.scene_meshes = self.scene.meshes(f.time)
            f.prims, f.reused = self._scene_maps(f.scene_meshes, f.camera, f.camera_key)
        f.report["scene_prims"] = {"meshes": len(f.scene_meshes), "reused": f.reused}
        with f.timed("shadows"):
            self._update_shadow_maps(f.scene_meshes, f.lights)
        f.report["shadows"] = {"maps_drawn": self.shadows.drawn, "casters": 0}
        if self._no_shadow:
            f.report["shadows"]["without_capsules"] = [p for p, _ in self._no_shadow]
            self._no_shadow = []
        return f.prims

    def _pose_stage(self, f: _FrameState) -> None:
        """Each character posed (its live pose and weights merged), its shadow capsules, its
        billboard; those in view become the frame's candidates. In the reference mode too:
        its skinned mesh then stands in for its network's maps (_evaluate_stage), lit,
        shadowed and composited as they would be, so that the two modes differ only there."""
        for character in self.characters:
            entry: dict[str, Any] = {"path": character.path}
            f.report["characters"].append(entry)
            with f.timed("rig"):
                candidate = self._pose_one(f, character, entry)
                if character.region_names and not self.reference:
                    entry["regions"] = self._place_regions(f, character, candidate)
            if candidate is not None:
                f.candidates.append(candidate)
                if self.reference:
                    entry.update(
                        decision="reference", reason="the skinned mesh, drawn by the renderer"
                    )

    def _pose_one(
        self, f: _FrameState, character: NeuralCharacter, entry: dict[str, Any]
    ) -> _Candidate | None:
        try:
            world = character.pose(f.time, self.live.local(character, f.time, entry))
            source = self._weights_of(character, f.time)
            weights = character.weights(f.time, source)
        except SceneError as exc:
            # One bad frame of animation must not end a sequence, nor draw a wrong image:
            # the character is left out of this frame, loudly.
            entry.update(decision="skipped", reason=exc.what)
            print(f"rigspace render: warning: {exc}", file=sys.stderr)
            return None
        posed = character.posed_capsules(world) if self._shadowing(f.lights) else None
        if posed is not None:  # casts a shadow wherever its billboard is, in view or not
            f.casters.append((character.path, posed))
        billboard = character.place(world, f.camera)
        if not billboard.visible:
            entry.update(decision="skipped", reason=billboard.reason)
            return None
        # The joints' world transforms and the camera determine the rig parameters and the
        # billboard, so they decide the reuse without computing the parameters.
        view = billboard.corners.round(3).tobytes() + f.camera_key
        region = billboard.region(f.camera)
        return _Candidate(
            character, entry, billboard, world, view, region, weights, character,
            character.path, source,
        )  # fmt: skip

    def _place_regions(
        self, f: _FrameState, character: NeuralCharacter, c: _Candidate | None
    ) -> list[dict[str, Any]]:
        """The report's entries of a character's regions this frame; those that add detail
        (region_skip) become candidates of its body (`c.regions`), evaluated with it. A
        region is placed only once its body is drawn: a skipped one runs nothing."""
        entries: list[dict[str, Any]] = []
        parts = {part.name: part for part in character.regions}
        for name in character.region_names:
            entry: dict[str, Any] = {"name": name}
            entries.append(entry)
            part = parts.get(name)
            if part is None:
                entry.update(decision="skipped", reason=character.region_problems[name])
                continue
            if c is None:
                entry.update(decision="skipped", reason="its character is not drawn this frame")
                continue
            billboard = part.place(c.world, f.camera)
            body_level = character.model.level_for(c.billboard.size_px, self.max_level)
            level = part.model.level_for(billboard.size_px, self.max_level)
            why = region_skip(c.billboard, body_level, billboard, level)
            if why:
                entry.update(decision="skipped", reason=why, size_px=round(billboard.size_px, 1))
                continue
            try:
                weights = character.weights(f.time, c.source_weights, part)
            except SceneError as exc:
                entry.update(decision="skipped", reason=exc.what)
                continue
            view = billboard.corners.round(3).tobytes() + f.camera_key
            c.regions.append(
                _Candidate(
                    character, entry, billboard, c.world, view, billboard.region(f.camera),
                    weights, part, f"{character.path}#{name}", c.source_weights,
                )
            )  # fmt: skip
        return entries

    def _evaluate_stage(self, f: _FrameState) -> None:
        """Each candidate's branches, its reuse of the last layer when pose, weights and view
        hold, and one network call per (model, level, branches) for the rest."""
        if self.reference:
            with f.timed("network"):  # the stage that makes the characters' maps
                self._mesh_layers(f)
            return
        pending: dict[tuple[int, int, tuple[str, ...]], list[_Candidate]] = {}
        for c in f.candidates:
            branches, why = self._branches(
                c, f.candidates, lambda: self._prims_stage(f).mask, bool(f.lights)
            )
            c.entry["mode"] = "lit" if "geometry" in branches else "unlit"
            c.entry["mode_reason"] = why
            self._plan(c, branches + _texture_branch(c.character), pending)
            for r in c.regions:  # its maps must have every map the body's have (merge_region)
                own = branches
                if branches != BOTH and not _albedo_alone(r.part):
                    own = BOTH
                r.entry["mode"] = c.entry["mode"]
                self._plan(r, own + _texture_branch(r.part), pending)
        with f.timed("rig"):
            for c in (c for group in pending.values() for c in group):
                c.rig = c.part.parameters(c.world, c.billboard, f.camera, c.weights)
        # One network call per (model, level, branches): characters sharing a bundle batch.
        # They run on the network thread, with the resampling of their maps into the frame,
        # while this one draws and lights the prims (render).
        f.pending = [
            (group, self._network.submit(self._evaluate, group, level, branches, f.camera))
            for (_, level, branches), group in pending.items()
        ]

    def _plan(
        self,
        c: _Candidate,
        branches: tuple[str, ...],
        pending: dict[tuple[int, int, tuple[str, ...]], list[_Candidate]],
    ) -> None:
        """A body's or region's reuse of its last layer when pose, weights and view hold, else
        its place in the network call of its (model, level, branches)."""
        cached = self._layers.get(c.key)
        if (
            cached is not None
            and cached.matches(c.world[c.part.order], c.view, c.billboard.side, c.weights)
            and set(branches) <= set(cached.layer.branches)
        ):
            c.entry.update(decision="reused", reason="same pose and camera as the last frame")
            return
        level = c.part.model.level_for(c.billboard.size_px, self.max_level)
        pending.setdefault((id(c.part.model), level, branches), []).append(c)

    @staticmethod
    def _evaluate(
        group: list[_Candidate], level: int, branches: tuple[str, ...], camera: Camera
    ) -> list[Layer]:
        """One network call for characters (or regions) sharing a bundle, level and branches,
        and each one's maps resampled into the frame (on the network thread)."""
        model = group[0].part.model
        out = model.predict(np.concatenate([c.rig for c in group]), level, branches)
        return [
            c.part.resample(
                {name: value[k : k + 1] for name, value in out.items()},
                c.billboard, camera, level, branches,
            )
            for k, c in enumerate(group)
        ]  # fmt: skip

    def _finish_evaluation(self, f: _FrameState) -> None:
        """The network calls' layers (waited for), kept for the frames that reuse them."""
        with f.timed("network"):
            for group, call in f.pending:
                for c, layer in zip(group, call.result(), strict=True):
                    self._layers[c.key] = _CachedLayer(
                        c.world[c.part.order], c.view, layer, weights=c.weights
                    )
                    c.entry.update(decision="evaluated", batch=len(group))
        if not self.reference:
            for c in f.candidates:
                self._describe(c, self._layers[c.key].layer)
                for r in c.regions:
                    self._describe(r, self._layers[r.key].layer)
        with f.timed("composite"):
            for c in f.candidates:
                self._drawn[c.key] = self._merged(c)

    def _merged(self, c: _Candidate) -> _CachedLayer:
        """A character's layer to light and composite: its body's, with the layers of the
        regions drawn this frame merged in by depth (runtime/regions.py; kept while the
        layers merged are the same)."""
        body = self._layers[c.key]
        if not c.regions:
            return body
        regions = [self._layers[r.key] for r in c.regions]
        key = (body.serial, *(r.serial for r in regions))
        kept = self._merges.get(c.key)
        if kept is not None and kept[0] == key:
            return kept[1]
        layer = body.layer
        for region in regions:
            layer = merge_region(layer, region.layer)
        merged = body if layer is body.layer else _CachedLayer(body.pose, body.view, layer)
        self._merges[c.key] = (key, merged)
        return merged

    def _mesh_layers(self, f: _FrameState) -> None:
        """The reference mode's layers: each candidate's skinned mesh (with its texture charts,
        the uv and chart AOVs to compare with) drawn alone over the whole frame."""
        if self._mesh_renderer is None:
            self._mesh_renderer = self._spec.create(RenderSettings(self._prim_samples))
        for c in f.candidates:
            meshes = c.character.rig.posed_meshes(
                f.time, charts=True, weights=self._weights_of(c.character, f.time)
            )
            maps = self._mesh_renderer.render(meshes, f.camera)
            layer = Layer(0, 0, maps.albedo, maps.mask, maps.depth, maps.normal, 0, BOTH,
                          uv=maps.uv, chart=maps.chart)  # fmt: skip
            self._layers[c.key] = _CachedLayer(
                c.world[c.character.order], c.view, layer, weights=c.weights
            )

    def _reused_composite(self, f: _FrameState) -> Frame:
        """The last frame's images with this frame's report: nothing it shows has changed."""
        assert self._frame is not None
        f.report["composite_reused"] = True
        f.report["scene_prims"]["lit_reused"] = True
        f.report.update(f.seconds())
        self._frame_at = f.time
        last = self._frame[1]
        f.report["background"] = last.report.get("background")
        return Frame(last.beauty, last.maps, f.report, last.opaque)

    def _light_prims_stage(self, f: _FrameState) -> np.ndarray:
        """The prims lit and shadowed (the maps' and the capsules' shadows): the beauty the
        characters are composited over. Still prims and lights reuse their lighting and only
        find the capsules' shadows again."""
        prims, camera, lights = self._prims_stage(f), f.camera, f.lights
        lit_key = f.light_key + self.shadows.key
        lit_reused = f.reused and self._lit_prims is not None and self._lit_prims[0] == lit_key
        if lit_reused and self._lit_prims is not None:
            with f.timed("shadows"):
                _, hidden = self._prim_shadows(
                    prims, camera, lights, f.scene_meshes, f.casters, False
                )
            with f.timed("lighting"):
                _, lit, visibility = self._lit_prims
                if lit is None:  # last shaded with the capsules' shadows in: once without them
                    lit = self._shade_prims(prims, camera, lights, visibility)
                    self._lit_prims = (lit_key, lit, visibility)
                beauty = lit.copy()  # the characters are composited over this copy
            with f.timed("shadows"):
                self._capsule_reshade(beauty, prims, camera, lights, hidden, visibility)
        else:
            # One pass finds the maps' and the capsules' shadows; one shading applies both.
            with f.timed("shadows"):
                visibility, hidden = None, []
                if self._shadowing(lights):
                    visibility, hidden = self._prim_shadows(
                        prims, camera, lights, f.scene_meshes, f.casters, True
                    )
            with f.timed("lighting"):
                both = visibility
                if any(v is not None for v in hidden) and visibility is not None:
                    both = [
                        m if c is None else c if m is None else m * c
                        for m, c in zip(visibility, hidden, strict=True)
                    ]
                beauty = self._shade_prims(prims, camera, lights, both)
                # Kept for a still next frame; without the capsules' shadows it is made then.
                lit = beauty.copy() if both is visibility else None
                self._lit_prims = (lit_key, lit, visibility)
        f.report["scene_prims"]["lit_reused"] = lit_reused
        return beauty

    def _composite_stage(self, f: _FrameState, beauty: np.ndarray) -> Frame:
        """Each character's layer lit (cached while its lights and the other casters hold)
        and composited into the beauty and the AOVs by depth; the DomeLight behind all."""
        prims, camera, lights = self._prims_stage(f), f.camera, f.lights
        albedo, normal = prims.albedo.copy(), prims.normal.copy()
        depth, mask = prims.depth.copy(), prims.mask.copy()
        # Texture AOVs (uv, chart) when anything has them: the reference mode's meshes, or a
        # character coloured from its textures.
        layers = [self._drawn[c.key].layer for c in f.candidates]
        uv = chart = None
        if prims.chart is not None or any(layer.chart is not None for layer in layers):
            shape = prims.mask.shape
            uv = prims.uv.copy() if prims.uv is not None else np.zeros((*shape, 2), np.float32)
            chart = prims.chart.copy() if prims.chart is not None else np.zeros(shape, np.int32)
        for c in f.candidates:
            cached = self._drawn[c.key]
            layer = cached.layer
            others = [(p, posed) for p, posed in f.casters if p != c.character.path]
            key = f.light_key + self.shadows.key + b"".join(posed.key for _, posed in others)
            if cached.lit is None or cached.lit_key != key:
                cached.lit_key = key
                with f.timed("shadows"):
                    visibility = self._layer_visibility(
                        layer, camera, lights, others, f.scene_meshes
                    )
                with f.timed("lighting"):
                    cached.lit = (
                        self._shade(
                            layer.albedo,
                            layer.normal,
                            layer.depth,
                            layer.mask,
                            camera,
                            lights,
                            origin=(layer.x0, layer.y0),
                            visibility=visibility,
                        )
                        if lights
                        else layer.albedo
                    )
            with f.timed("composite"):
                composite(layer, cached.lit, beauty, albedo, normal, depth, mask, uv, chart)
        with f.timed("composite"):
            dome = next((light for light in lights if light.kind == AMBIENT), None)
            f.report["background"] = dome.path if dome is not None else None
            if dome is not None:  # behind everything: over it goes the premultiplied frame
                over_background(beauty, mask, self._dome_background(dome, camera, f.camera_key))
        f.report["shadows"]["maps_drawn"] = self.shadows.drawn  # drawn when first needed
        for array in (beauty, albedo, normal, depth, mask, uv, chart):
            if array is not None:
                array.flags.writeable = False  # shared with the frame cache
        return Frame(
            beauty, Maps(albedo, normal, depth, mask, uv, chart), f.report, dome is not None
        )

    def coverage_of(self, path: str, time: float) -> np.ndarray | None:
        """(H, W) a character's own coverage at `time`, before any depth test: its layer's in
        the last frame, rendered at `time` (None when it was not drawn); in the reference mode
        its skinned mesh's, drawn alone (what `--reference` measures the network's silhouette
        against)."""
        character = next((c for c in self.characters if c.path == path), None)
        if character is None:
            return None
        camera, _ = self._camera_at(time)
        cached = self._drawn.get(path)
        if cached is None:
            return None
        layer = cached.layer
        full = np.zeros((camera.height, camera.width), np.float32)
        h, w = layer.mask.shape
        full[layer.y0 : layer.y0 + h, layer.x0 : layer.x0 + w] = layer.mask
        return full

    def _repeat(self, last: Frame, start: float) -> Frame:
        """The last frame again, its report saying so."""
        report = {**last.report, "repeat_of_last_frame": True, "composite_reused": True}
        report["characters"] = [_repeated(e) for e in last.report["characters"]]
        report["counts"] = _counts(report["characters"])
        report["seconds"] = _seconds(dict.fromkeys(STAGES, 0.0), start)
        return Frame(last.beauty, last.maps, report, last.opaque)

    def use_shadow_backend(self, backend: ShadowBackend) -> None:
        """Compute the shadows with `backend` from the next call on (the shadow maps drawn so
        far are kept: the shadow bench times both kernels on the same inputs)."""
        self._compiled = shadow_pass.COMPILED if backend.kernel == "numba" else None
        self.shadows.use(backend, self._compiled)

    def set_weights(self, path: str, weights: dict[str, float]) -> None:
        """Override blend shape weights of the character at `path` from the next frame on (an
        empty dict clears them). A name the character's meshes lack, or a weight that is not a
        finite number, is a ValueError naming it."""
        character = next((c for c in self.characters if c.path == path), None)
        if character is None:
            raise ValueError(f"{path} is not a neural character of this stage")
        for name, value in weights.items():
            if name not in character.rig.blend_shapes:
                raise ValueError(f"{path} has no blend shape {name!r}")
            if not isinstance(value, int | float) or not np.isfinite(value):
                raise ValueError(f"the weight of {name!r} must be a finite number")
        before = self.weight_overrides.get(path)
        if weights:
            self.weight_overrides[path] = {k: float(v) for k, v in weights.items()}
        else:
            self.weight_overrides.pop(path, None)
        if self.weight_overrides.get(path) != before:
            self._frame_at = None  # the same time code is not the same frame any more

    def _weights_of(self, character: NeuralCharacter, time: float) -> np.ndarray | None:
        """The character's blend shape weights (its order) with live sources' and then the
        overrides' merged in; None when neither applies (the animation's)."""
        weights = self.live.weights(character, time)
        override = self.weight_overrides.get(character.path)
        if override:
            if weights is None:
                weights = character.rig.blend_weights(time)
            for name, value in override.items():
                weights[character.rig.blend_shapes.index(name)] = value
        return weights

    def _describe(self, c: _Candidate, layer: Layer) -> None:
        top = max(c.part.model.resolutions)
        c.entry.update(
            level=layer.level,
            top_level=top,
            level_reason=(
                f"capped by max_level {self.max_level}, upsampled to its "
                f"{c.billboard.size_px:.0f} px"
                if self.max_level is not None and layer.level < c.billboard.size_px
                else f"the largest level, upsampled to its {c.billboard.size_px:.0f} px"
                if c.billboard.size_px > top
                else f"the smallest level covering its {c.billboard.size_px:.0f} px"
            ),
            branches=list(layer.branches),
            colour=(
                f"its textures on {100 * layer.info['textured']:.1f}% of its pixels, the albedo "
                "branch on the rest"
                if "textured" in layer.info
                else "the albedo branch"
                if "albedo" in layer.branches
                else "none (the albedo branch did not run)"
            ),
            size_px=round(c.billboard.size_px, 1),
            region=[int(layer.x0), int(layer.y0), *map(int, layer.mask.shape[::-1])],
            **({"texture_ms": layer.info["texture_ms"]} if "texture_ms" in layer.info else {}),
        )


def _texture_branch(part: NeuralPart) -> tuple[str, ...]:
    """("texture",) when the character's (or region's) texture head is a branch of its own
    and the scene has its textures (the frame runs it beside the map branches), else ()."""
    own = part.model.texture_branch == "texture"
    return ("texture",) if own and part.textures is not None else ()


def _albedo_alone(part: NeuralPart) -> bool:
    """Whether the albedo branch alone gives a part's maps in the unlit mode: coverage from
    its alpha (bundle format 2 on), colour not from a texture head on the geometry branch."""
    on_geometry = part.textures is not None and part.model.texture_branch == "geometry"
    return part.model.albedo_has_alpha and not on_geometry


@dataclass
class _FrameState:
    """One frame's context, filled stage by stage (Engine.render)."""

    time: float
    start: float
    """perf_counter() when the frame began (the report's total)."""
    cpu: bool = False
    """Whether `timed` also adds the process's CPU seconds to `cpu_timings` (report_cpu)."""
    timings: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    cpu_timings: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    camera: Camera = field(init=False)
    camera_key: bytes = b""
    scene_meshes: list = field(default_factory=list)
    """The set's meshes (the shadow casters), without the reference mode's characters."""
    prims: Maps | None = None
    """The prims' G-buffer, once _prims_stage has drawn it."""
    reused: bool = False
    """Whether the prims' G-buffer is the last frame's."""
    lights: list = field(default_factory=list)
    light_key: bytes = b""
    report: dict[str, Any] = field(default_factory=dict)
    casters: list[tuple[str, PosedCapsules]] = field(default_factory=list)
    candidates: list[_Candidate] = field(default_factory=list)
    pending: list[tuple[list[_Candidate], Future]] = field(default_factory=list)
    """The network calls under way: (the characters, the call making their layers)."""

    @contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Add the time the block takes to the report's seconds of `stage`."""
        began = clock.perf_counter()
        cpu = clock.process_time() if self.cpu else 0.0
        try:
            yield
        finally:
            self.timings[stage] += clock.perf_counter() - began
            if self.cpu:
                self.cpu_timings[stage] += clock.process_time() - cpu

    def seconds(self) -> dict[str, Any]:
        """The report's timings: `seconds` per stage and in total, and with `cpu` the stages'
        `cpu_seconds`."""
        timings = {"seconds": _seconds(self.timings, self.start)}
        if self.cpu:
            timings["cpu_seconds"] = {k: round(v, 6) for k, v in self.cpu_timings.items()}
        return timings


@dataclass
class _Candidate:
    """A character whose billboard is in view this frame, before its maps are known; or one
    of its regions that adds detail this frame (in its body's `regions`)."""

    character: NeuralCharacter
    entry: dict[str, Any]
    """Its entry in the report (a region's: in its character's entry's "regions")."""
    billboard: Billboard
    world: np.ndarray
    """(J, 4, 4) joint-to-world transforms."""
    view: bytes
    region: tuple[int, int, int, int]
    """(x0, y0, w, h) of the billboard in the frame."""
    weights: np.ndarray
    """(B,) blend shape weights in the model's order (empty: it reads none)."""
    part: NeuralPart
    """What draws it: the character itself (its body), or one of its regions."""
    key: str
    """Its layer's key in the engine's caches: the character's path, PATH#NAME a region's."""
    source_weights: np.ndarray | None = None
    """The character's blend shape weights from live sources and overrides (its order;
    None: the animation's), from which each region takes its own."""
    rig: np.ndarray | None = None
    """Rig parameters, computed only for the characters evaluated this frame."""
    regions: list[_Candidate] = field(default_factory=list)
    """Its regions evaluated (or reused) this frame, merged into its layer."""


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


def _check_request(aovs: tuple[str, ...], width: int, height: int) -> None:
    """Refuse unknown AOVs and an empty viewport (a SceneError naming the fix)."""
    unknown = sorted(set(aovs) - set(AOVS))
    if unknown:
        raise SceneError(f"Unknown AOV {', '.join(unknown)}.", f"choose from {', '.join(AOVS)}.")
    if width <= 0 or height <= 0:
        raise SceneError(
            f"The viewport is {width}x{height}.",
            "render at least 1x1 pixels (--resolution WxH).",
        )


def _world_points(depth, rows, cols, normal, camera: Camera, origin):
    """Planar (3, N) float32 world positions and normals of pixels (rows, cols) of a region
    at `origin`, from their camera-space depth and (N, 3) normals."""
    d = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    x = (cols.astype(np.float32) + np.float32(origin[0] + 0.5 - camera.cx)) * (d / camera.fx)
    y = (np.float32(camera.cy - origin[1] - 0.5) - rows.astype(np.float32)) * (d / camera.fy)
    z = -d
    m = camera.camera_to_world.astype(np.float32)
    n = np.ascontiguousarray(normal.T, dtype=np.float32)
    points = np.stack([m[i, 0] * x + m[i, 1] * y + m[i, 2] * z + m[i, 3] for i in range(3)])
    normals = np.stack([m[i, 0] * n[0] + m[i, 1] * n[1] + m[i, 2] * n[2] for i in range(3)])
    return points, normals


def _seconds(timings: dict[str, float], start: float) -> dict[str, float]:
    """The report's seconds per stage, and the total since `start`."""
    seconds = {k: round(v, 6) for k, v in timings.items()}
    seconds["total"] = round(clock.perf_counter() - start, 6)
    return seconds


def _window(regions: list[tuple[int, int, int, int]]) -> tuple[slice, slice]:
    """The frame rows and columns holding every region (x0, y0, x1, y1)."""
    return (
        slice(min(r[1] for r in regions), max(r[3] for r in regions)),
        slice(min(r[0] for r in regions), max(r[2] for r in regions)),
    )


def _in_frame(pixels: np.ndarray, window: tuple[slice, slice], camera: Camera) -> np.ndarray:
    """Flat indices of a window's pixels as flat indices of the frame."""
    rows, cols = np.divmod(pixels, window[1].stop - window[1].start)
    return (rows + window[0].start) * camera.width + cols + window[1].start


def _rect(region: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) as (x0, y0, w, h)."""
    return region[0], region[1], region[2] - region[0], region[3] - region[1]


def _overlaps(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


def _repeated(entry: dict[str, Any]) -> dict[str, Any]:
    """A report entry (a character's, or a region's) of a frame repeated unchanged."""
    if "regions" in entry:
        entry = {**entry, "regions": [_repeated(r) for r in entry["regions"]]}
    if entry["decision"] in ("evaluated", "reused"):
        return {**entry, "decision": "reused", "reason": REPEATED}
    return entry


REPEATED = "same time code as the last frame, stage unedited"


def _counts(entries: list[dict[str, Any]]) -> dict[str, int]:
    """How many characters each decision applied to in a frame (the report's summary), and
    how many of their regions."""
    counts = dict.fromkeys(("evaluated", "reused", "skipped", "reference"), 0)
    counts |= {"outside the view": 0, "unlit": 0, "below the largest level": 0}
    counts |= dict.fromkeys(("regions evaluated", "regions reused", "regions skipped"), 0)
    for e in entries:
        counts[e["decision"]] += 1
        if e.get("reason") == "outside the view":
            counts["outside the view"] += 1
        if e.get("mode") == "unlit":
            counts["unlit"] += 1
        if "level" in e and e["level"] < e["top_level"]:
            counts["below the largest level"] += 1
        for region in e.get("regions", ()):
            counts[f"regions {region['decision']}"] += 1
    return counts


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

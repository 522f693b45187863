"""The characters' stages: each neural character posed, its billboard placed, the branches it
needs decided, its layer reused or its network run (batched per bundle, level and branches, on
network threads beside the frame's), and its regions' layers merged into its body's
(runtime/regions.py)."""

from __future__ import annotations

import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from rigspace.runtime.character import Layer, NeuralCharacter, NeuralPart
from rigspace.runtime.frame import CachedLayer, Candidate, FrameCaches, FrameState
from rigspace.runtime.live.engine import LiveInput
from rigspace.runtime.regions import merge_regions, region_skip
from rigspace.runtime.settings import EngineSettings
from rigspace.runtime.shadows.frame import casts_shadows
from rigspace.sdk.camera import Camera
from rigspace.sdk.errors import SceneError
from rigspace.sdk.render import RendererSpec, RenderSettings

BOTH = ("albedo", "geometry")
Plan = dict[tuple[int, int, tuple[str, ...]], list[Candidate]]
"""The network calls of a frame: per (model, level, branches), the candidates it evaluates."""
NETWORK_WORKERS = 2
"""Threads running the frame's network calls: a character's regions' networks run beside its
body's rather than after it. The film shot (a body and three regions, 162 frames on 2 cores,
alternating in one sitting): 84.1, 84.9, 84.2 ms a frame against 88.4, 90.5, 94.8 with one
thread, the body alone 78.4 (samples/film_character/README.md)."""


class CharacterStages:
    """Poses the characters (`pose`), runs or reuses their networks (`evaluate`, `finish`)."""

    def __init__(
        self,
        characters: list[NeuralCharacter],
        live: LiveInput,
        settings: EngineSettings,
        spec: RendererSpec,
        caches: FrameCaches,
        weight_overrides: dict[str, dict[str, float]],
        shared: object = None,
    ) -> None:
        """`shared`: the device resources the reference mode's renderer draws with
        (RenderSettings.shared: the engine's GL context)."""
        self.characters, self.live, self.settings = characters, live, settings
        self._shared = shared
        self.caches, self.weight_overrides = caches, weight_overrides
        self._spec = spec
        self._network = ThreadPoolExecutor(NETWORK_WORKERS, thread_name_prefix="rigspace-network")
        """Runs the frame's network calls while the frame's thread draws and lights the prims."""
        self._locks: dict[int, threading.Lock] = {}
        """One per model (by id): its calls run one at a time (its sessions and its parts'
        resampling buffers are not shared between threads), other models' beside them."""
        self._mesh_renderer: Any = None
        """The reference mode's renderer of the characters' meshes (their own: the prims'
        keeps its uploads while they are drawn apart)."""

    def close(self) -> None:
        self._network.shutdown(wait=True)
        if self._mesh_renderer is not None:
            self._mesh_renderer.close()
            self._mesh_renderer = None

    def pose(self, f: FrameState) -> None:
        """Each character posed (its live pose and weights merged), its shadow capsules, its
        billboard; those in view become the frame's candidates. In the reference mode too:
        its skinned mesh then stands in for its network's maps (`evaluate`), lit, shadowed
        and composited as they would be, so that the two modes differ only there."""
        reference = self.settings.reference
        for character in self.characters:
            entry: dict[str, Any] = {"path": character.path}
            f.report.characters.append(entry)
            with f.timed("rig"):
                candidate = self._pose_one(f, character, entry)
                if character.region_names and not reference:
                    entry["regions"] = self._place_regions(f, character, candidate)
            if candidate is not None:
                f.candidates.append(candidate)
                if reference:
                    entry.update(
                        decision="reference", reason="the skinned mesh, drawn by the renderer"
                    )

    def _pose_one(
        self, f: FrameState, character: NeuralCharacter, entry: dict[str, Any]
    ) -> Candidate | None:
        try:
            world = character.pose(f.time, self.live.local(character, f.time, entry))
            source = self.weights_of(character, f.time)
            weights = character.weights(f.time, source)
        except SceneError as exc:
            # One bad frame of animation must not end a sequence, nor draw a wrong image:
            # the character is left out of this frame, loudly.
            entry.update(decision="skipped", reason=exc.what)
            print(f"rigspace render: warning: {exc}", file=sys.stderr)
            return None
        posed = character.posed_capsules(world) if casts_shadows(f.lights) else None
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
        return Candidate(
            character, entry, billboard, world, view, region, weights, character,
            character.path, source,
        )  # fmt: skip

    def _place_regions(
        self, f: FrameState, character: NeuralCharacter, c: Candidate | None
    ) -> list[dict[str, Any]]:
        """The report's entries of a character's regions this frame; those that add detail
        (region_skip) become candidates of its body (`c.regions`), evaluated with it. A
        region is placed only once its body is drawn: a skipped one runs nothing."""
        entries: list[dict[str, Any]] = []
        parts = {part.name: part for part in character.regions}
        max_level = self.settings.max_level
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
            body_level = character.model.level_for(c.billboard.size_px, max_level)
            level = part.model.level_for(billboard.size_px, max_level)
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
                Candidate(
                    character, entry, billboard, c.world, view, billboard.region(f.camera),
                    weights, part, f"{character.path}#{name}", c.source_weights,
                )
            )  # fmt: skip
        return entries

    def weights_of(self, character: NeuralCharacter, time: float) -> np.ndarray | None:
        """The character's blend shape weights and controls (`rig.scalar_names` order; a live
        source's blend shape weights alone where no override names a control) with live
        sources' and then the overrides' merged in; None when neither applies (the stage's)."""
        weights = self.live.weights(character, time)
        override = self.weight_overrides.get(character.path)
        if override:
            rig = character.rig
            if weights is None:
                weights = rig.scalars(time)
            elif len(weights) == len(rig.blend_shapes) and rig.controls:
                weights = np.concatenate([weights, rig.control_values(time)])
            for name, value in override.items():
                weights[rig.scalar_names.index(name)] = value
        return weights

    def needs_coverage(self, f: FrameState) -> bool:
        """Whether a candidate's branches depend on the prims' coverage behind its billboard
        (`evaluate` then needs the prims' G-buffer drawn first)."""
        if self.settings.reference:
            return False
        return any(self._branches_alone(c, bool(f.lights)) is None for c in f.candidates)

    def _branches_alone(self, c: Candidate, lit: bool) -> tuple[tuple[str, ...], str] | None:
        """The map branches a character needs this frame and why, where that does not depend
        on what overlaps its billboard (None: it does; `_branches`)."""
        if lit:
            return BOTH, "lights reach it: normals and depth are shaded"
        if c.character.textures is not None and c.character.model.texture_branch == "geometry":
            return BOTH, "its texture head is on the geometry branch"
        if {"normal", "depth"} & set(self.settings.aovs):
            return BOTH, "the normal or depth AOV is asked for"
        if not c.character.model.albedo_has_alpha:
            return BOTH, "its bundle (format 1) takes coverage from the geometry branch"
        return None

    def _branches(
        self, c: Candidate, candidates: list[Candidate], coverage: np.ndarray | None, lit: bool
    ) -> tuple[tuple[str, ...], str]:
        """The map branches a character needs this frame, and why (the unlit mode's decision):
        `coverage`, the prims', is given where `needs_coverage` said so."""
        alone = self._branches_alone(c, lit)
        if alone is not None:
            return alone
        assert coverage is not None, "needs_coverage said the prims were not needed"
        x0, y0, w, h = c.region
        if np.any(coverage[y0 : y0 + h, x0 : x0 + w] > 0):
            return BOTH, "a scene prim overlaps its billboard: depth-tested"
        if any(_overlaps(c.region, o.region) for o in candidates if o is not c):
            return BOTH, "another character overlaps its billboard: depth-tested"
        return ("albedo",), "no lights and nothing overlapping its billboard"

    def evaluate(self, f: FrameState, coverage: np.ndarray | None) -> None:
        """Each candidate's branches, its reuse of the last layer when pose, weights and view
        hold, and one network call per (model, level, branches) for the rest, sent to the
        network thread. `coverage`: the prims' (H, W), where `needs_coverage` asked for it."""
        if self.settings.reference:
            with f.timed("network"):  # the stage that makes the characters' maps
                self._mesh_layers(f)
            return
        pending: Plan = {}
        for c in f.candidates:
            branches, why = self._branches(c, f.candidates, coverage, bool(f.lights))
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
                c.entry.update(c.part.novel_view(c.rig))
        # One network call per (model, level, branches): characters sharing a bundle batch.
        # They run on the network threads (a model's calls one at a time), with the resampling
        # of their maps into the frame, while the frame's thread draws and lights the prims
        # (Engine.render).
        f.pending = []
        for (key, level, branches), group in pending.items():
            lock = self._locks.setdefault(key, threading.Lock())
            call = self._network.submit(_evaluate, group, level, branches, f.camera, lock)
            f.pending.append((group, call))

    def _plan(self, c: Candidate, branches: tuple[str, ...], pending: Plan) -> None:
        """A body's or region's reuse of its last layer when pose, weights and view hold, else
        its place in the network call of its (model, level, branches)."""
        cached = self.caches.layers.get(c.key)
        if (
            cached is not None
            and cached.matches(c.world[c.part.order], c.view, c.billboard.side, c.weights)
            and set(branches) <= set(cached.layer.branches)
        ):
            c.entry.update(decision="reused", reason="same pose and camera as the last frame")
            return
        level = c.part.model.level_for(c.billboard.size_px, self.settings.max_level)
        pending.setdefault((id(c.part.model), level, branches), []).append(c)

    def finish(self, f: FrameState) -> None:
        """The network calls' layers (waited for), kept for the frames that reuse them, and
        each character's layer to draw (its regions merged in)."""
        layers = self.caches.layers
        with f.timed("network"):
            for group, call in f.pending:
                for c, layer in zip(group, call.result(), strict=True):
                    layers[c.key] = CachedLayer(
                        c.world[c.part.order], c.view, layer, weights=c.weights
                    )
                    c.entry.update(decision="evaluated", batch=len(group))
        if not self.settings.reference:
            for c in f.candidates:
                self._describe(c, layers[c.key].layer)
                for r in c.regions:
                    self._describe(r, layers[r.key].layer)
        with f.timed("composite"):
            for c in f.candidates:
                self.caches.drawn[c.key] = self._merged(c)

    def _merged(self, c: Candidate) -> CachedLayer:
        """A character's layer to light and composite: its body's, with the layers of the
        regions drawn this frame merged in by depth (runtime/regions.py; kept while the
        layers merged are the same)."""
        body = self.caches.layers[c.key]
        if not c.regions:
            return body
        regions = [self.caches.layers[r.key] for r in c.regions]
        key = (body.serial, *(r.serial for r in regions))
        kept = self.caches.merges.get(c.key)
        if kept is not None and kept[0] == key:
            return kept[1]
        layer = merge_regions(body.layer, [r.layer for r in regions])
        merged = body if layer is body.layer else CachedLayer(body.pose, body.view, layer)
        self.caches.merges[c.key] = (key, merged)
        return merged

    def _mesh_layers(self, f: FrameState) -> None:
        """The reference mode's layers: each candidate's skinned mesh (with its texture charts,
        the uv and chart AOVs to compare with) drawn alone over the whole frame."""
        if self._mesh_renderer is None:
            samples = self.settings.prim_samples
            self._mesh_renderer = self._spec.create(RenderSettings(samples, shared=self._shared))
        for c in f.candidates:
            weights = self.weights_of(c.character, f.time)
            if weights is not None:  # the meshes take the blend shapes; controls are inputs
                weights = weights[: len(c.character.rig.blend_shapes)]
            meshes = c.character.rig.posed_meshes(f.time, charts=True, weights=weights)
            maps = self._mesh_renderer.render(meshes, f.camera)
            layer = Layer(0, 0, maps.albedo, maps.mask, maps.depth, maps.normal, 0, BOTH,
                          uv=maps.uv, chart=maps.chart)  # fmt: skip
            self.caches.layers[c.key] = CachedLayer(
                c.world[c.character.order], c.view, layer, weights=c.weights
            )

    def _describe(self, c: Candidate, layer: Layer) -> None:
        """A drawn body's or region's report entry: its level and why, branches, colour."""
        top = max(c.part.model.resolutions)
        size = c.billboard.size_px
        max_level = self.settings.max_level
        c.entry.update(
            level=layer.level,
            top_level=top,
            level_reason=(
                f"capped by max_level {max_level}, upsampled to its {size:.0f} px"
                if max_level is not None and layer.level < size
                else f"the largest level, upsampled to its {size:.0f} px"
                if size > top
                else f"the smallest level covering its {size:.0f} px"
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
            size_px=round(size, 1),
            region=[int(layer.x0), int(layer.y0), *map(int, layer.mask.shape[::-1])],
            **({"texture_ms": layer.info["texture_ms"]} if "texture_ms" in layer.info else {}),
        )


def _evaluate(
    group: list[Candidate],
    level: int,
    branches: tuple[str, ...],
    camera: Camera,
    lock: threading.Lock,
) -> list[Layer]:
    """One network call for characters (or regions) sharing a bundle, level and branches,
    and each one's maps resampled into the frame (on a network thread, holding the model's
    lock)."""
    with lock:
        model = group[0].part.model
        out = model.predict(np.concatenate([c.rig for c in group]), level, branches)
        return [
            c.part.resample(
                {name: value[k : k + 1] for name, value in out.items()},
                c.billboard, camera, level, branches,
            )
            for k, c in enumerate(group)
        ]  # fmt: skip


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


def _overlaps(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]

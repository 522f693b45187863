"""One neural character per frame: pose -> rig parameters -> network -> maps in the frame.

The steps of the paper's scene composition, for one character and one camera:
1. joint world rotations at time t from the stage (CharacterRig), in the model's joint
   order; a live source may pass its own local transforms instead (the seam);
2. the billboard at the look-at joint (runtime/billboard.py) and the virtual camera C R;
3. rig parameters q^ in that frame, 6D; the smallest level of detail that covers the
   billboard's on-screen size; only the branches the frame needs;
4. the maps re-seen from the camera's distance to the joint, each pixel moved by the
   parallax of its depth offset (runtime/parallax.py: the network drew the joint from its
   training distance), then warped into the frame through the billboard's homography,
   mask-aware (the unlit mode runs the albedo branch alone and takes coverage from its
   alpha, and has no depth to move its pixels by): normals and depth are warped
   premultiplied by coverage and divided back, so empty pixels never bleed in; normals
   rotated by R into the render camera's frame; depth = the billboard plane plus the
   network's offset. Coverage magnified past the network's
   resolution gets its edge back to one frame pixel (sdk.texturing.sharpen_coverage);
5. colour: with a texture head (bundle `texture`), the character's own textures sampled
   where the network says each pixel lands, at the size on screen (rigspace.sdk.texturing);
   the albedo branch, un-premultiplied, where no texture drives the colour or the chart is
   unsure (and for bundles without a head); premultiplied by the coverage.
Only the billboard's screen bounding box is computed.

A region of the character with a network of its own (the face, a hand: docs/regions.md) goes
through the same steps with its own bundle (a NeuralPart, as the body is): its own billboard
at its own joint, its own level, the same rig parameter path in its manifest's joint and shape
order; runtime/regions.py merges its maps into the body's before the lighting.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Usd, UsdGeom, Vt

from rigspace.runtime.billboard import Billboard, TrainingView, place
from rigspace.runtime.parallax import reseen
from rigspace.runtime.shadows import PosedCapsules, chains, pose_capsules
from rigspace.sdk import schema
from rigspace.sdk.bundle import BundleError
from rigspace.sdk.camera import Camera
from rigspace.sdk.capsules import CapsuleError, read_capsules
from rigspace.sdk.errors import RigspaceError, SceneError
from rigspace.sdk.model import BundleModel
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.rotations import joint_up, rig_inputs, rig_parameters
from rigspace.sdk.texturing import (
    ChartTextures,
    TextureMismatch,
    display_colour,
    magnification,
    region_warper,
    sharpen_coverage,
)
from rigspace.sdk.view_coverage import (
    NOVEL_VIEW_DEG,
    ViewCoverage,
    ViewCoverageError,
    read_views,
)

COVERAGE_EPSILON = 1e-4
"""Warped coverage below this counts as empty (divisions by coverage are guarded by it)."""


@dataclass
class Layer:
    """A character's maps in a frame region [y0:y0+h, x0:x0+w]; albedo is premultiplied."""

    x0: int
    y0: int
    albedo: np.ndarray | None
    mask: np.ndarray
    depth: np.ndarray | None
    normal: np.ndarray | None
    level: int
    branches: tuple[str, ...]
    info: dict = field(default_factory=dict)
    uv: np.ndarray | None = None
    """(h, w, 2) the texture st each pixel read (0 where the albedo branch coloured it), with
    a texture head; None without."""
    chart: np.ndarray | None = None
    """(h, w) int32 the texture chart each pixel read (0: none)."""


def joint_order(model_joints: list[str], skeleton_joints: list[str], where: str) -> np.ndarray:
    """Indices into the skeleton's joints of the model's joints, or a SceneError naming the missing."""
    order, missing = [], []
    for name in model_joints:
        try:
            order.append(schema.find_joint(name, skeleton_joints))
        except schema.JointLookupError:
            missing.append(name)
    if missing:
        raise SceneError(
            f"{where}: the model reads joints the skeleton lacks: {', '.join(missing)}.",
            "bind the skeleton the model was trained on, or retrain on this skeleton.",
        )
    return np.asarray(order)


def blend_order(model_shapes: tuple[str, ...], shapes: tuple[str, ...], where: str) -> np.ndarray:
    """Indices into the character's blend shapes of the model's, or a SceneError naming the
    missing. A character's shapes the model does not read are left out (they do not change
    what it draws)."""
    missing = [name for name in model_shapes if name not in shapes]
    if missing:
        raise SceneError(
            f"{where}: the model reads blend shapes the character's meshes lack: "
            f"{', '.join(missing)}.",
            "bind the meshes the model was trained on (their skel:blendShapes), or retrain on "
            "this character.",
        )
    return np.array([shapes.index(name) for name in model_shapes], dtype=np.int64)


def scalar_order(model: BundleModel, rig: CharacterRig, where: str) -> np.ndarray:
    """Indices into the character's rig vector after the joints (`CharacterRig.scalar_names`:
    blend shapes, then controls) of what the model reads there (its blend shapes, then its
    controls), or a SceneError naming what the character lacks."""
    shapes = blend_order(model.blend_shapes, rig.blend_shapes, where)
    names = [c.name for c in rig.controls]
    missing = [name for name in model.controls if name not in names]
    if missing:
        raise SceneError(
            f"{where}: the model reads controls the character does not declare: "
            f"{', '.join(missing)}.",
            "apply RigspaceControlAPI:NAME for each (rigspace inspect names them), or retrain "
            "on this character.",
        )
    controls = [len(rig.blend_shapes) + names.index(name) for name in model.controls]
    return np.concatenate([shapes, np.array(controls, dtype=np.int64)])


class NeuralPart:
    """What one model bundle draws of a neural character: the whole body (NeuralCharacter
    itself), or a region of it with a network of its own (the face, a hand; docs/regions.md).
    Each has its own joint and blend shape order (its manifest's), its own billboard at its
    own look-at joint with its own training view, its own levels, and its own texture
    sampling of the character's textures; the steps from pose to maps are the same."""

    def __init__(
        self,
        rig: CharacterRig,
        model: BundleModel,
        where: str,
        up: np.ndarray,
        name: str = "body",
        look_at: str = "",
        shared: NeuralPart | None = None,
    ) -> None:
        """`where` names the part in errors ("Neural character /World/Hero"); `up` is the
        stage's up axis; `look_at` the joint a manifest without look_at_joint looks at
        (default: the skeleton's first); `shared`: a part (the body) whose textures this one
        samples too when the two bundles' chart tables are the same."""
        self.model = model
        self.name = name
        """"body", or the region's name."""
        manifest = model.manifest
        self.order = joint_order(model.joints, rig.joints, where)
        self.scalar_order = scalar_order(model, rig, where)
        """Indices into the character's blend shapes and controls (`rig.scalar_names`) of the
        model's (its input order after the joints)."""
        self.look_at = schema.find_joint(
            manifest.look_at_joint or look_at or rig.joints[0], rig.joints
        )
        if manifest.training_distance <= 0:
            raise BundleError(
                f"Model bundle {manifest.folder}: manifest.json has no training_camera.",
                "re-export the bundle with `rigspace train`; the manifest is incomplete.",
            )
        self.view = TrainingView(
            manifest.training_distance,
            manifest.training_focal_length,
            manifest.training_aperture,
        )
        self.training_resolution = manifest.training_resolution or max(model.resolutions)
        self.up = up
        """The stage's up axis: the training ring kept it upright in every view."""
        self.upright_axis = (
            np.asarray(manifest.training_upright, np.float64) if manifest.training_upright else None
        )
        """The look-at joint's own up (its local frame) that a region's ring kept upright
        instead (`upright = "joint"`), None for the stage's: its billboard turns with the
        joint."""
        self.textures: ChartTextures | None = None
        """Its meshes' textures by texture chart, when its bundle has a texture head."""
        self._chart_table: dict | None = None
        self.no_texture = self._load_textures(rig, shared)
        """Why its colour comes from the albedo branch alone ("" when it samples textures)."""
        self.views: ViewCoverage | None = None
        """The training views of its look-at joint (sdk.view_coverage), when its bundle has
        them: each evaluation's distance to them goes in the frame's report."""
        self.no_views = self._load_views()
        """Why its frames report no novel views ("" when they do)."""

    def _load_views(self) -> str:
        section = self.model.manifest.views
        if section is None:
            return (
                "its model bundle has no training views (views.npy; `python -m "
                "rigspace.apps.views BUNDLE DATASET` adds them)"
            )
        try:
            self.views = read_views(self.model.manifest.folder, section, len(self.model.joints))
        except ViewCoverageError as exc:
            return str(exc)
        return ""

    def novel_view(self, rig: np.ndarray) -> dict[str, Any]:
        """The report's account of how far rig row `rig`'s view of the look-at joint lies
        outside the views its network learned, and which way when it is novel (empty without
        training views)."""
        if self.views is None:
            return {}
        degrees, way = self.views.outside(rig)
        far = degrees > NOVEL_VIEW_DEG
        return {"novel_view_deg": round(degrees, 1), **({"novel_view": way} if far else {})}

    def _load_textures(self, rig: CharacterRig, shared: NeuralPart | None = None) -> str:
        """Its texture charts over the character's textures; those of `shared` (the body)
        when the two bundles' chart tables are the same (the textures are read once)."""
        if not self.model.charts:
            return "its model bundle has no texture head"
        try:
            table = self.model.chart_table()
        except BundleError as exc:  # a damaged charts.json: the albedo branch still draws it
            return str(exc)
        assert table is not None  # the bundle has charts
        self._chart_table = table
        if shared is not None and shared.textures is not None and shared._chart_table == table:
            self.textures = shared.textures
            return ""
        sources = {rig.mesh_name(m): m for m in rig.mesh_sources()}
        try:
            textures = ChartTextures.build(table, sources)
        except TextureMismatch as exc:
            return (
                f"{exc} (the scene's character is not the one its bundle was trained on; retrain "
                "on this character, or restore its meshes)"
            )
        if not textures.any_texture:
            return "none of its meshes has a texture"
        self.textures = textures
        return ""

    def place(self, world: np.ndarray, camera: Camera) -> Billboard:
        """Its billboard at its look-at joint, upright as its training ring's cameras were: to
        the stage's up, or to the joint's own (`upright_axis`; the stage's where the camera
        looks along it, as the ring's did)."""
        joint = world[self.look_at]
        scale = float(np.cbrt(abs(np.linalg.det(joint[:3, :3]))))
        # Joint scale is the character's own world scale (the rig has no joint scaling).
        if self.upright_axis is None:
            return place(joint[:3, 3], camera, self.view, scale, self.up)
        own = joint_up(joint, self.upright_axis)
        return place(joint[:3, 3], camera, self.view, scale, own, fallback_up=self.up)

    def parameters(
        self,
        world: np.ndarray,
        billboard: Billboard,
        camera: Camera,
        weights: np.ndarray | None = None,
    ) -> np.ndarray:
        """(1, J*6 + B + C) the network's input: the joints' rotations in the virtual camera,
        then the blend shape weights and the controls' values (`weights`, model order) when the
        model reads any."""
        virtual = np.eye(4)
        virtual[:3, :3] = billboard.virtual_camera_to_world(camera)
        rotations = rig_parameters(world[self.order], virtual)[None]
        return rig_inputs(rotations, None if weights is None else np.asarray(weights)[None])

    def finish_geometry(
        self,
        coverage: np.ndarray,
        normal_w: np.ndarray,
        offset_w: np.ndarray,
        billboard: Billboard,
        camera: Camera,
        origin: tuple[int, int],
        kernel: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mask, normals and depth over the region from the warped coverage and the normals
        and depth offsets warped premultiplied by it (compiled; `kernel` False: numpy's
        geometry_reference, which the kernel is tested against)."""
        offset_scale = self.model.depth_scale * billboard.side / self.view.side
        if not kernel:
            return geometry_reference(
                coverage, normal_w, offset_w, billboard, camera, origin, offset_scale
            )
        from rigspace.runtime.resample_kernel import finish_geometry

        h, w = coverage.shape
        mask = np.empty((h, w), np.float32)
        normal = np.empty((h, w, 3), np.float32)
        depth = np.empty((h, w), np.float32)
        finish_geometry(
            coverage, normal_w, offset_w, np.ascontiguousarray(billboard.rotation, np.float64),
            float(-billboard.rotation[:, 2] @ billboard.joint_camera), offset_scale, origin[0],
            origin[1], camera.cx, camera.cy, camera.fx, camera.fy, COVERAGE_EPSILON, mask,
            normal, depth,
        )  # fmt: skip
        return mask, normal, depth

    def resample(self, out, billboard: Billboard, camera: Camera, level: int, branches) -> Layer:
        # The network drew its joint from its training distance; the camera sees it from
        # its own (runtime/parallax.py: each pixel moved by its depth offset's parallax).
        scale = billboard.side / self.view.side
        out = reseen(
            out,
            self.view.distance * scale,
            float(np.linalg.norm(billboard.joint_camera)),
            self.model.depth_scale * scale,
        )
        out = {name: value[0] for name, value in out.items()}  # the batch of one
        x0, y0, w, h = billboard.region(camera)
        homography = billboard.homography(level)  # network pixels -> frame pixels
        warp = region_warper(homography, (x0, y0, w, h))
        mask = None
        albedo = depth = normal = None
        info: dict = {}
        if "geometry" in branches:
            coverage = warp(out["mask"])[..., 0]
            normal_w = warp(out["normal"] * out["mask"])
            offset_w = warp(out["depth"] * out["mask"])[..., 0]
            mask, normal, depth = self.finish_geometry(
                coverage, normal_w, offset_w, billboard, camera, (x0, y0)
            )
        if mask is None and "alpha" in out:  # the unlit mode: coverage from the albedo branch
            mask = np.clip(warp(out["alpha"])[..., 0], 0.0, 1.0)
        if mask is None:
            raise ValueError(
                "no coverage: run the geometry branch, or the albedo branch of a format-2 bundle"
            )
        uv = chart = None
        if "albedo" in branches:
            albedo, sharp, info = display_colour(
                out, homography, (x0, y0, w, h), mask, self.textures
            )
            sample = info.pop("sample", None)
            if sample is not None:
                uv, chart = sample.st, sample.chart
        else:
            sharp = sharpen_coverage(mask, magnification(homography, (x0, y0, w, h)))
        return Layer(x0, y0, albedo, sharp, depth, normal, level, tuple(branches), info, uv, chart)


class NeuralCharacter(NeuralPart):
    """A RigspaceNeuralCharacter prim with its loaded model, evaluated per frame: its body is
    this NeuralPart; its regions (`load_regions`), each a NeuralPart of its own bundle, are
    drawn over it (runtime/regions.py)."""

    def __init__(self, prim: Usd.Prim, model: BundleModel) -> None:
        self.prim = prim
        self.path = str(prim.GetPath())
        self.rig = CharacterRig(prim)
        axis = UsdGeom.GetStageUpAxis(prim.GetStage())
        up = np.array([0.0, 0.0, 1.0]) if axis == UsdGeom.Tokens.z else np.array([0.0, 1.0, 0.0])
        super().__init__(self.rig, model, f"Neural character {self.path}", up)
        self.capsules: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        """Shadow capsules (skeleton joint index, a, b, radius), None without any."""
        self.no_shadow = self._load_capsules(model.manifest.capsules)
        """Why the character casts no shadow ("" when it has capsules)."""
        self.regions: list[NeuralPart] = []
        """Its regions drawn by their own bundles (load_regions), in its manifest's order."""
        self.region_problems: dict[str, str] = {}
        """Region name -> why it is not drawn (its bundle could not be loaded, or regions are
        turned off): every region its manifest lists is in `regions` or here once
        load_regions ran."""

    @property
    def region_names(self) -> tuple[str, ...]:
        """The regions its bundle lists (manifest `regions`), in order."""
        return tuple(r.name for r in self.model.manifest.regions)

    def load_regions(self, open_model: Callable[[Path], BundleModel]) -> list[str]:
        """Each region its bundle lists as a NeuralPart of its own bundle, opened by
        `open_model(folder)` (the engine's: the body's precision and predictor, sessions
        shared between characters). A region whose bundle cannot be used (no manifest, a graph
        missing or damaged, a joint or shape the character lacks) is left out, and the body
        draws without it: returned is one warning per such region, naming the region, the file
        and the fix."""
        warnings = []
        for region in self.model.manifest.regions:
            where = f"Neural character {self.path}, region {region.name}"
            try:
                model = open_model(region.folder)
                part = NeuralPart(
                    self.rig, model, where, self.up, region.name, region.joint, shared=self
                )
            except schema.JointLookupError as exc:
                problem = f"{where}: its bundle looks at a joint the skeleton lacks ({exc})"
                fix = "retrain the regions on this character's skeleton"
            except RigspaceError as exc:
                problem, fix = exc.what, exc.fix
            else:
                self.regions.append(part)
                continue
            self.region_problems[region.name] = f"its bundle cannot be used: {problem}"
            fix = f"{fix.rstrip('.')}; or " if fix else ""
            warnings.append(
                f"{self.path}: region {region.name} is not drawn, the body draws without it: "
                f"its bundle {region.folder} cannot be used: {problem} Fix: {fix}train the "
                "regions again (`rigspace train DATASET --out "
                f"{self.model.manifest.folder}` on a dataset captured with `rigspace capture "
                "--regions` writes regions/NAME), or draw the body alone (--no-regions)."
            )
        return warnings

    def _load_capsules(self, name: str | None) -> str:
        if not name:
            return "its model bundle has no shadow capsules (capsules.json)"
        try:
            capsules = read_capsules(self.model.manifest.folder / str(name))
        except CapsuleError as exc:
            return str(exc)
        try:
            joints = [schema.find_joint(j, self.rig.joints) for j in capsules.joints]
        except schema.JointLookupError as exc:
            return f"its shadow capsules name a joint the skeleton lacks ({exc})"
        self.capsules = (np.asarray(joints), capsules.a, capsules.b, capsules.radius)
        self._chains = chains([self.rig.joints[j] for j in joints])
        return ""

    def posed_capsules(self, world: np.ndarray) -> PosedCapsules | None:
        """The shadow capsules at joint transforms `world` (J, 4, 4), in world space."""
        if self.capsules is None:
            return None
        joints, a, b, radius = self.capsules
        return pose_capsules(a, b, radius, world[joints], self._chains)

    def pose(self, time: float, local: Vt.Matrix4dArray | None = None) -> np.ndarray:
        """(J, 4, 4) joint-to-world transforms at `time` (from `local` when a source gives it)."""
        world = self.rig.world_transforms(time, local)
        if not np.all(np.isfinite(world)):
            raise SceneError(
                f"Neural character {self.path}: the animation gives NaN or Inf joint transforms at "
                f"time {time:g}.",
                "fix the SkelAnimation's values at that time (or the live source's data).",
            )
        return world

    def weights(
        self, time: float, live: np.ndarray | None = None, part: NeuralPart | None = None
    ) -> np.ndarray:
        """(B + C,) the blend shape weights and the controls' values the model reads at
        `time`, in its order: the stage's (the animation's weights, the controls' values), or
        `live` (the character's `rig.scalar_names` order, from a live source or an override)
        where given; a `live` of the blend shape weights alone takes the stage's controls.
        `part`: those one of its regions reads, in its model's order (default: the body's)."""
        part = part or self
        if not len(part.scalar_order):
            return np.zeros(0, dtype=np.float32)
        if live is None:
            weights = self.rig.scalars(time)
        else:
            weights = np.asarray(live, np.float32)
            if len(weights) == len(self.rig.blend_shapes) and self.rig.controls:
                weights = np.concatenate([weights, self.rig.control_values(time)])
        weights = weights[part.scalar_order]
        if not np.all(np.isfinite(weights)):
            names = (*part.model.blend_shapes, *part.model.controls)
            column = int(np.argmax(~np.isfinite(weights)))
            if column < len(part.model.blend_shapes):
                what, fix = f"blend shape {names[column]} has", "SkelAnimation's blendShapeWeights"
            else:
                what, fix = (
                    f"control {names[column]} has",
                    f"rigspace:control:{names[column]}:value",
                )
            raise SceneError(
                f"Neural character {self.path}: {what} a NaN or Inf value at time {time:g}.",
                f"fix the {fix} at that time (or the live source's).",
            )
        return weights


def geometry_reference(
    coverage: np.ndarray,
    normal_w: np.ndarray,
    offset_w: np.ndarray,
    billboard: Billboard,
    camera: Camera,
    origin: tuple[int, int],
    offset_scale: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NeuralCharacter.finish_geometry in numpy (the reference its kernel is tested against):
    normals and depth divided back by the coverage, so empty pixels never bleed in; normals
    rotated into the render camera's frame; depth the billboard plane plus the offset."""
    mask = np.clip(coverage, 0.0, 1.0)
    weight = np.maximum(coverage, COVERAGE_EPSILON)[..., None]
    has = coverage > COVERAGE_EPSILON
    normal_r = (normal_w / weight) @ billboard.rotation.T  # virtual camera -> render camera
    length = np.linalg.norm(normal_r, axis=-1, keepdims=True)
    # A zero-length prediction (int8 graphs round all three components to zero on a few
    # covered pixels) faces the camera rather than shading black.
    facing = np.array([0.0, 0.0, 1.0], dtype=normal_r.dtype)
    valid = length > COVERAGE_EPSILON
    normal_r = np.where(valid, normal_r, facing)
    normal = np.where(has[..., None], normal_r / np.where(valid, length, 1.0), 0.0)
    offset = offset_w / weight[..., 0] * offset_scale
    plane = billboard.plane_depth(camera, offset, origin=origin)
    depth = np.where(has, plane, np.inf).astype(np.float32)
    return mask.astype(np.float32), normal.astype(np.float32), depth

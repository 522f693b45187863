"""Read USD meshes into what a renderer draws: triangles, per-corner UVs, and albedo.

Albedo follows UsdPreviewSurface: `diffuseColor` connected to a UsdUVTexture (its file
read through USD's asset resolver, so textures inside .usdz packages work; 8-bit images
and sourceColorSpace "sRGB" are decoded to linear; scale and bias applied) with the UV
set named by the UsdPrimvarReader_float2 feeding it, else `diffuseColor`'s value, else
primvars:displayColor, else 18% grey. Textures wrap as wrapS and wrapT say (repeat,
mirror, clamp, black; useMetadata, the fallback, is repeat: PNG and JPEG carry no wrap
metadata, and repeat is what the renderers always did). A file path with `<UDIM>` reads
every tile found (UsdShade.UdimUtils) into one atlas image, which the uv reach through an
affine transform (Albedo.uv_scale, uv_offset), so renderers sample it as one texture.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from pxr import Ar, Sdf, Usd, UsdGeom, UsdShade

from rigspace.sdk.color import srgb_to_linear
from rigspace.sdk.errors import SceneError
from rigspace.sdk.render import DEFAULT_COLOR, DrawMesh, freeze


def triangulate(counts: np.ndarray, indices: np.ndarray, left_handed: bool = False):
    """Fan-triangulate USD polygons.

    Returns (triangles (T,3) point indices, corners (T,3) positions in faceVertexIndices,
    faces (T,) the polygon of each triangle). Polygons with fewer than 3 vertices are
    skipped; left-handed meshes get their winding flipped to counter-clockwise.
    """
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    per_face = np.where(counts >= 3, counts - 2, 0)
    faces = np.repeat(np.arange(len(counts)), per_face)
    k = np.arange(per_face.sum()) - np.repeat(np.cumsum(per_face) - per_face, per_face)
    first = starts[faces]
    corners = np.stack([first, first + k + 1, first + k + 2], axis=1)
    if left_handed:
        corners = corners[:, [0, 2, 1]]
    return indices[corners].astype(np.int32), corners, faces


def subdivide_triangles(
    points: np.ndarray,
    triangles: np.ndarray,
    corner_uv: np.ndarray,
    vertex: dict[str, np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """One midpoint step: (P, 3) points, (T, 3) triangles, (3T, 2) face-varying uvs and
    per-vertex arrays (P, k) -> 4T triangles; each edge's midpoint gets the mean of its ends'
    vertex values. Triangle t becomes 4t..4t+3 (corners first, the middle one last)."""
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = len(points) + inverse.reshape(-1, 3)  # (T, 3): midpoints of edges ab, bc, ca
    new_points = np.concatenate([points, points[unique].mean(axis=1)])
    a, b, c = triangles.T
    ab, bc, ca = mid.T
    tris = np.stack(
        [np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))],
        axis=1,
    ).reshape(-1, 3)
    uv = corner_uv.reshape(-1, 3, 2)
    ua, ub, uc = uv[:, 0], uv[:, 1], uv[:, 2]
    uab, ubc, uca = (ua + ub) / 2, (ub + uc) / 2, (uc + ua) / 2
    new_uv = np.stack(
        [
            np.stack(t, axis=1)
            for t in ((ua, uab, uca), (uab, ub, ubc), (uca, ubc, uc), (uab, ubc, uca))
        ],
        axis=1,
    ).reshape(-1, 2)
    values = {k: np.concatenate([v, v[unique].mean(axis=1)]) for k, v in vertex.items()}
    return new_points, tris, new_uv, values


def dense_skin_weights(indices: np.ndarray, weights: np.ndarray, joints: int) -> np.ndarray:
    """(P, k) UsdSkel joint indices and weights -> (P, joints) one weight per joint (what
    subdivide_triangles interpolates at a midpoint)."""
    dense = np.zeros((len(indices), joints), dtype=np.float32)
    np.add.at(dense, (np.arange(len(indices))[:, None], indices), weights)
    return dense


def sparse_skin_weights(dense: np.ndarray, influences: int) -> tuple[np.ndarray, np.ndarray]:
    """(P, joints) weights -> the `influences` largest per point as UsdSkel's (P, k) int32
    joint indices and float32 weights, renormalised to sum to 1."""
    top = np.argsort(-dense, axis=1)[:, :influences]
    weights = np.take_along_axis(dense, top, axis=1)
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    return top.astype(np.int32), weights.astype(np.float32)


def _primvar_per_corner(primvar: UsdGeom.Primvar, triangles, corners, faces, time=None):
    """A primvar's values at every triangle corner, shape (T, 3, k), whatever its interpolation."""
    values = primvar.ComputeFlattened(Usd.TimeCode.Default() if time is None else time)
    if values is None or len(values) == 0:
        return None
    values = np.asarray(values, dtype=np.float32)
    values = values.reshape(len(values), -1)
    interpolation = primvar.GetInterpolation()
    if interpolation == UsdGeom.Tokens.faceVarying:
        index = corners
    elif interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
        index = triangles
    elif interpolation == UsdGeom.Tokens.uniform:
        index = np.repeat(faces[:, None], 3, axis=1)
    else:  # constant
        index = np.zeros_like(triangles)
    if index.max(initial=0) >= len(values):
        raise SceneError(
            f"Primvar {primvar.GetAttr().GetPath()} has {len(values)} values, too few for its "
            f"{interpolation} interpolation.",
            "re-export the mesh; its primvar does not match its topology.",
        )
    return values[index]


def read_texture(asset, color_space: str = "auto", where: str = "") -> np.ndarray:
    """A texture as linear float32 RGB (H, W, 3), read through USD's asset resolver.

    `where` names what uses it (material, shader and prim) in the errors.
    """
    resolved = asset.resolvedPath if hasattr(asset, "resolvedPath") else str(asset)
    used_by = f" ({where})" if where else ""
    if not resolved:
        raise SceneError(
            f"Texture @{getattr(asset, 'path', asset)}@{used_by} does not resolve.",
            "correct the shader's inputs:file (a relative path is relative to the layer that "
            "authors it) or put the image there.",
        )
    data = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(resolved))
    if data is None:
        raise SceneError(
            f"Texture {resolved}{used_by} cannot be opened.", "check that the file exists."
        )
    image = cv2.imdecode(np.frombuffer(data.GetBuffer(), np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SceneError(
            f"Texture {resolved}{used_by} is not an image OpenCV can decode.",
            "re-save it as PNG.",
        )
    # OpenCV decodes to uint8, uint16, or float32 (EXR, HDR: already linear).
    integer = image.dtype in (np.uint8, np.uint16)
    image = image.astype(np.float32) / (
        255.0 if image.dtype == np.uint8 else 65535.0 if integer else 1.0
    )
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    image = image[:, :, 2::-1] if image.shape[2] >= 3 else np.repeat(image[:, :, :1], 3, axis=2)
    if color_space == "sRGB" or (color_space == "auto" and integer):
        image = srgb_to_linear(image)
    return np.ascontiguousarray(image)


WRAP_MODES = ("repeat", "mirror", "clamp", "black")
"""UsdUVTexture wrapS / wrapT values the renderers and the runtime's sampler implement, in
the order of their codes (Albedo.wrap_codes)."""


@dataclass
class Albedo:
    """Where a mesh's albedo comes from: a texture with a UV set, or colours."""

    color: np.ndarray
    """(3,) constant or (N, 3) per point, linear."""
    texture: np.ndarray | None = None
    """(H, W, 3) linear, UsdUVTexture scale and bias already applied (a UDIM texture: its
    tiles in one atlas, tile 1001 at the bottom left)."""
    uv_set: str = "st"
    wrap: tuple[str, str] = ("repeat", "repeat")
    """UsdUVTexture wrapS, wrapT (WRAP_MODES)."""
    uv_scale: tuple[float, float] = (1.0, 1.0)
    uv_offset: tuple[float, float] = (0.0, 0.0)
    """The texture is sampled at st * uv_scale + uv_offset: the identity, except for a UDIM
    atlas, whose tiles [u0, u0 + nu) x [v0, v0 + nv) it maps onto [0, 1]^2."""
    udim: bool = False

    @property
    def wrap_codes(self) -> tuple[int, int]:
        return WRAP_MODES.index(self.wrap[0]), WRAP_MODES.index(self.wrap[1])


def read_udim_atlas(
    source: AlbedoTexture, color_space: str
) -> tuple[np.ndarray, tuple[float, float], tuple[float, float]]:
    """A UDIM texture's tiles in one atlas image, and the uv scale and offset that map st onto
    it: tile 1001 + u + 10 v covers st [u, u+1) x [v, v+1). Tiles of other sizes are resized
    to the largest (bilinear); missing tiles in the atlas's rectangle stay black."""
    tiles = source.udim_tiles()
    if not tiles:
        raise SceneError(
            f"UDIM texture @{source.file.path}@ ({source.where}) has no tile on disk.",
            "put its tiles (name.1001.png, ...) beside the layer, or correct inputs:file.",
        )
    images = {
        tile: read_texture(Sdf.AssetPath(path, path), color_space, f"{source.where}, tile {tile}")
        for path, tile in tiles
    }
    height = max(i.shape[0] for i in images.values())
    width = max(i.shape[1] for i in images.values())
    cells = {tile: ((tile - 1001) % 10, (tile - 1001) // 10) for tile in images}
    u0 = min(c[0] for c in cells.values())
    v0 = min(c[1] for c in cells.values())
    nu = max(c[0] for c in cells.values()) - u0 + 1
    nv = max(c[1] for c in cells.values()) - v0 + 1
    atlas = np.zeros((nv * height, nu * width, 3), np.float32)
    for tile, image in images.items():
        if image.shape[:2] != (height, width):
            image = cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR)
        u, v = cells[tile]
        row = (nv - 1 - (v - v0)) * height  # v grows upwards; image rows downwards
        col = (u - u0) * width
        atlas[row : row + height, col : col + width] = image
    return atlas, (1.0 / nu, 1.0 / nv), (-u0 / nu, -v0 / nv)


def _input_source(shader_input: UsdShade.Input):
    """The shader and output an input is connected to, or None."""
    if not shader_input or not shader_input.HasConnectedSource():
        return None
    source, _output, _kind = shader_input.GetConnectedSource()
    return UsdShade.Shader(source.GetPrim())


def _shader_id(shader: UsdShade.Shader) -> str:
    return str(shader.GetIdAttr().Get() or "") if shader else ""


@dataclass(frozen=True)
class AlbedoTexture:
    """A UsdUVTexture feeding a UsdPreviewSurface's diffuseColor, and who uses it."""

    prim: str
    material: str
    shader: UsdShade.Shader
    reader: UsdShade.Shader | None
    """The UsdPrimvarReader_float2 feeding its st, if any."""

    @property
    def file(self):
        """The authored inputs:file (an Sdf.AssetPath), or None."""
        file_input = self.shader.GetInput("file")
        return file_input.Get() if file_input else None

    @property
    def where(self) -> str:
        return (
            f"inputs:file of {self.shader.GetPath()} in material {self.material}, bound to "
            f"{self.prim}"
        )

    def problem(self) -> str | None:
        """Why the image cannot be found (without reading it), or None."""
        asset = self.file
        if asset is None or not asset.path:
            return f"{self.where} is empty"
        if UsdShade.UdimUtils.IsUdimIdentifier(asset.path):
            if not self.udim_tiles():
                return f"UDIM texture @{asset.path}@ ({self.where}) has no tile on disk"
            return None
        if not asset.resolvedPath:
            return f"texture @{asset.path}@ ({self.where}) does not resolve"
        return None

    def udim_tiles(self) -> list[tuple[str, int]]:
        """(resolved path, tile number) of every tile of a `<UDIM>` file path found on disk."""
        attribute = self.shader.GetInput("file").GetAttr()
        stack = attribute.GetPropertyStack(Usd.TimeCode.Default())
        layer = stack[0].layer if stack else Sdf.Layer.CreateAnonymous()
        found = UsdShade.UdimUtils.ResolveUdimTilePaths(self.file.path, layer)
        return sorted((str(path), int(tile)) for path, tile in found)

    def wrap(self) -> tuple[str, str]:
        """wrapS, wrapT as WRAP_MODES (useMetadata and unauthored: repeat)."""
        modes = []
        for name in ("wrapS", "wrapT"):
            value = self.shader.GetInput(name)
            token = str(value.Get()) if value and value.Get() is not None else "useMetadata"
            if token not in (*WRAP_MODES, "useMetadata"):
                raise SceneError(
                    f"inputs:{name} of {self.shader.GetPath()} is {token!r}.",
                    f"author one of {', '.join(WRAP_MODES)} or useMetadata.",
                )
            modes.append("repeat" if token == "useMetadata" else token)
        return modes[0], modes[1]


def _surface(prim: Usd.Prim) -> tuple[UsdShade.Material | None, UsdShade.Shader | None]:
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    surface = material.ComputeSurfaceSource()[0] if material else None
    if surface and _shader_id(surface) == "UsdPreviewSurface":
        return material, surface
    return material, None


def albedo_texture(prim: Usd.Prim) -> AlbedoTexture | None:
    """The texture a gprim's UsdPreviewSurface reads its diffuseColor from, or None."""
    material, surface = _surface(prim)
    if material is None or surface is None:
        return None
    texture = _input_source(surface.GetInput("diffuseColor"))
    if not texture or _shader_id(texture) != "UsdUVTexture":
        return None
    return AlbedoTexture(
        prim=str(prim.GetPath()),
        material=str(material.GetPath()),
        shader=texture,
        reader=_input_source(texture.GetInput("st")),
    )


def read_albedo(prim: Usd.Prim) -> Albedo:
    """The albedo of a gprim per UsdPreviewSurface rules, falling back to displayColor."""
    _material, surface = _surface(prim)
    if surface is not None:
        diffuse = surface.GetInput("diffuseColor")
        source = albedo_texture(prim)
        if source is not None:
            texture = source.shader
            color_space = texture.GetInput("sourceColorSpace")
            reader = source.reader
            uv_set = "st"
            if reader and reader.GetInput("varname"):
                uv_set = str(reader.GetInput("varname").Get() or "st")
            if source.file is None:
                raise SceneError(
                    f"Texture {source.where} is empty.", "author the image's path in inputs:file."
                )
            space = str(color_space.Get()) if color_space and color_space.Get() else "auto"
            wrap = source.wrap()
            uv_scale, uv_offset, udim = (1.0, 1.0), (0.0, 0.0), False
            if UsdShade.UdimUtils.IsUdimIdentifier(source.file.path):
                image, uv_scale, uv_offset = read_udim_atlas(source, space)
                wrap, udim = ("clamp", "clamp"), True
            else:
                image = read_texture(source.file, space, source.where)
            scale, bias = texture.GetInput("scale"), texture.GetInput("bias")
            if scale and scale.Get() is not None:
                image = image * np.asarray(scale.Get(), np.float32)[:3]
            if bias and bias.Get() is not None:
                image = image + np.asarray(bias.Get(), np.float32)[:3]
            return Albedo(
                color=np.asarray(DEFAULT_COLOR, np.float32),
                texture=np.ascontiguousarray(image, dtype=np.float32),
                uv_set=uv_set,
                wrap=wrap,
                uv_scale=uv_scale,
                uv_offset=uv_offset,
                udim=udim,
            )
        if diffuse and diffuse.Get() is not None and not diffuse.HasConnectedSource():
            return Albedo(color=np.asarray(diffuse.Get(), np.float32))
    display = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    if display and display.HasValue():
        values = np.asarray(display.ComputeFlattened(), np.float32).reshape(-1, 3)
        if display.GetInterpolation() in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
            return Albedo(color=values)
        # constant, uniform and faceVarying colours: their mean (renderers take point colours)
        return Albedo(color=values.mean(axis=0))
    return Albedo(color=np.asarray(DEFAULT_COLOR, np.float32))


@dataclass
class MeshSource:
    """What does not change over time in a mesh: topology, UVs, albedo."""

    path: str
    rest_points: np.ndarray
    triangles: np.ndarray
    corner_uv: np.ndarray | None
    albedo: Albedo

    def __post_init__(self) -> None:
        # Read-only: renderers cache by identity what never changes (DrawMesh, frozen).
        color = self.albedo.color if isinstance(self.albedo.color, np.ndarray) else None
        freeze(self.rest_points, self.triangles, self.corner_uv, self.albedo.texture, color)

    def draw_mesh(self, points: np.ndarray, normals: np.ndarray | None = None) -> DrawMesh:
        """The mesh with these (posed, world-space) points, ready for a renderer."""
        return DrawMesh(
            points=points,
            normals=normals,
            triangles=self.triangles,
            corner_uv=self.corner_uv,
            texture=self.albedo.texture,
            color=self.albedo.color,
            name=self.path,
            wrap=self.albedo.wrap_codes,
            uv_scale=self.albedo.uv_scale,
            uv_offset=self.albedo.uv_offset,
        )


def _topology(prim: Usd.Prim, time: Usd.TimeCode | None):
    """A mesh's points and its triangles, with each triangle's corners and face."""
    mesh = UsdGeom.Mesh(prim)
    when = Usd.TimeCode.Default() if time is None else time
    points = mesh.GetPointsAttr().Get(when)
    counts = mesh.GetFaceVertexCountsAttr().Get(when)
    indices = mesh.GetFaceVertexIndicesAttr().Get(when)
    if points is None or counts is None or indices is None or len(points) == 0:
        raise SceneError(
            f"Mesh {prim.GetPath()} has no points or faces.",
            "author points, faceVertexCounts and faceVertexIndices (or deactivate the prim).",
        )
    left = mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    triangles, corners, faces = triangulate(counts, indices, left)
    if len(indices) and int(np.max(indices)) >= len(points):
        raise SceneError(
            f"Mesh {prim.GetPath()} indexes point {int(np.max(indices))} of {len(points)}.",
            "re-export the mesh; its faceVertexIndices are out of range.",
        )
    return np.asarray(points, dtype=np.float32), triangles, corners, faces


def _part(
    prim: Usd.Prim, name: str, topology, albedo: Albedo, keep: np.ndarray | None = None
) -> MeshSource:
    """The triangles `keep` selects (all: None) of a mesh with the albedo of their material."""
    points, triangles, corners, faces = topology
    corner_uv = None
    if albedo.texture is not None:
        primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar(albedo.uv_set)
        if primvar and primvar.HasValue():
            corner_uv = _primvar_per_corner(primvar, triangles, corners, faces)
        if corner_uv is None or corner_uv.shape[-1] != 2:
            raise SceneError(
                f"Mesh {prim.GetPath()} has a texture but no 2-component primvar "
                f"{albedo.uv_set!r} to map it.",
                f"author primvars:{albedo.uv_set} (texCoord2f[]) or change the UsdPrimvarReader's "
                "varname to the mesh's UV set.",
            )
    if albedo.color.ndim == 2 and len(albedo.color) != len(points):
        albedo.color = albedo.color.mean(axis=0)
    if keep is not None:
        triangles = triangles[keep]
        corner_uv = None if corner_uv is None else corner_uv[keep]
    return MeshSource(
        path=name, rest_points=points, triangles=triangles, corner_uv=corner_uv, albedo=albedo
    )


def read_mesh_source(prim: Usd.Prim, time: Usd.TimeCode | None = None) -> MeshSource:
    """Topology, UVs and albedo of a UsdGeom.Mesh (points at `time`, default: the default time),
    with the material bound to the mesh itself."""
    return _part(prim, str(prim.GetPath()), _topology(prim, time), read_albedo(prim))


def read_mesh_parts(prim: Usd.Prim, time: Usd.TimeCode | None = None) -> list[MeshSource]:
    """A mesh split by its materials: one part per material-bind GeomSubset (named by the
    subset's path, with the subset's bound material) and one for the faces no subset takes
    (named by the mesh's path, with the mesh's own); a mesh without subsets is one part.
    The parts share the mesh's points (their triangles index them), so a skinned mesh is
    skinned once for all of its parts."""
    subsets = UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets()
    if not subsets:
        return [read_mesh_source(prim, time)]
    topology = _topology(prim, time)
    faces = topology[3]
    taken = np.zeros(len(faces), bool)
    parts = []
    albedos: dict[str, Albedo] = {}  # subsets bound to one material share its texture's array
    for subset in subsets:
        indices = np.asarray(subset.GetIndicesAttr().Get(Usd.TimeCode.Default()) or [], np.int64)
        keep = np.isin(faces, indices) & ~taken  # a face in two subsets: the first one's
        taken |= keep
        if keep.any():
            material, _ = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()
            key = str(material.GetPath()) if material else str(subset.GetPath())
            if key not in albedos:
                albedos[key] = read_albedo(subset.GetPrim())
            parts.append(_part(prim, str(subset.GetPath()), topology, albedos[key], keep))
    if not taken.all():
        parts.append(_part(prim, str(prim.GetPath()), topology, read_albedo(prim), ~taken))
    return parts

"""The paper's premise, measured: a character's mesh path grows with its triangles, the
network's cost does not.

The sample character (22,956 triangles) is subdivided 1 -> 4 triangles per step (edge
midpoints: skin weights, vertex colours and face-varying uvs interpolated, each new point's
four largest joint influences kept and renormalised), giving about 23k, 92k, 367k, 1.5M and
5.9M triangles, each written as a copy of the character that the previs shot references. Per
frame of the shot at 640x360 (the character about 340 px tall), two engines over the same
stage: `reference=True` draws the skinned mesh (UsdSkel blend shapes and skinning, normals,
the renderer's raster and shading, in the frame's "scene" stage), the default draws the
network's maps (the albedo branch's colour: the subdivided meshes' uvs are not the ones the
bundle's texture charts were made for). Both are timed on the same frames, one after the
other; memory is the posed
mesh's arrays a frame hands the renderer plus the stage's mesh data, against the bundle's
graphs.
"""

from __future__ import annotations

import itertools
import shutil
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.bench.scenes import PREVIS
from rigspace.sdk.geometry import dense_skin_weights, sparse_skin_weights
from rigspace.sdk.geometry import subdivide_triangles as subdivide

CHARACTER = PREVIS.parent.parent / "character" / "sample_character.usda"
MESH = "/Character/Body"
INFLUENCES = 4
TIMES = (100.0, 500.0, 900.0, 1300.0)
"""Frames of the shot (walk, stretch, roll, yoga): the character near the middle of the frame."""


def heavy_scene(folder: Path, steps: int) -> tuple[Path, int]:
    """The previs shot with its character subdivided `steps` times (files in `folder`);
    returns the scene and the character's triangle count."""
    from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

    folder.mkdir(parents=True, exist_ok=True)
    character = folder / "character.usda"
    layer = Sdf.Layer.FindOrOpen(str(CHARACTER))
    layer.Export(str(character))
    shutil.copytree(CHARACTER.parent / "textures", folder / "textures", dirs_exist_ok=True)
    stage = Usd.Stage.Open(str(character))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(MESH))
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    primvars = UsdGeom.PrimvarsAPI(mesh)
    points = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
    triangles = np.array(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    st = primvars.GetPrimvar("st")
    uv = np.array(st.Get(), dtype=np.float64)
    if st.GetIndices():
        uv = uv[np.array(st.GetIndices())]
    colour = np.array(primvars.GetPrimvar("displayColor").Get(), dtype=np.float64)
    joints = len(UsdSkel.Skeleton(stage.GetPrimAtPath("/Character/Skel")).GetJointsAttr().Get())
    indices = np.array(binding.GetJointIndicesPrimvar().Get()).reshape(-1, INFLUENCES)
    weights = np.array(binding.GetJointWeightsPrimvar().Get()).reshape(-1, INFLUENCES)
    vertex = {"skin": dense_skin_weights(indices, weights, joints), "colour": colour}
    for _ in range(steps):
        points, triangles, uv, vertex = subdivide(points, triangles, uv, vertex)
    indices, weights = sparse_skin_weights(vertex["skin"], INFLUENCES)
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(triangles), 3, np.int32)))
    mesh.GetFaceVertexIndicesAttr().Set(
        Vt.IntArray.FromNumpy(triangles.reshape(-1).astype(np.int32))
    )
    st.GetAttr().Set(Vt.Vec2fArray.FromNumpy(uv.astype(np.float32)))
    if st.GetIndices():
        st.GetIndicesAttr().Clear()
    primvars.GetPrimvar("displayColor").Set(
        Vt.Vec3fArray.FromNumpy(vertex["colour"].astype(np.float32))
    )
    binding.GetJointIndicesPrimvar().Set(Vt.IntArray.FromNumpy(indices.reshape(-1)))
    binding.GetJointWeightsPrimvar().Set(Vt.FloatArray.FromNumpy(weights.reshape(-1)))
    mesh.GetExtentAttr().Clear()
    stage.GetRootLayer().Save()
    scene = folder / "previs.usda"
    text = PREVIS.read_text().replace("@../character/sample_character.usda@", "@character.usda@")
    text = text.replace("@../models/sample@", f"@{(PREVIS.parent.parent / 'models' / 'sample')}@")
    scene.write_text(text.replace("@../", f"@{PREVIS.parent.parent}/"))
    return scene, len(triangles)


def _mesh_bytes(engine) -> int:
    """What the mesh path holds for a frame: the posed arrays handed to the renderer plus the
    rig's rest data (points, triangles, uvs, skin weights as read)."""
    total = 0
    for character in engine.characters:
        for mesh in character.rig.posed_meshes(TIMES[0]):
            total += sum(
                a.nbytes for a in (mesh.points, mesh.normals, mesh.triangles) if a is not None
            )
            total += 0 if mesh.corner_uv is None else mesh.corner_uv.nbytes
        for part in character.rig.mesh_sources():
            total += part.rest_points.nbytes + part.triangles.nbytes
        total += sum(
            np.array(q.GetJointIndicesPrimvar().Get()).nbytes * 2
            for q in (m.query for m in character.rig._meshes)
        )
    return total


def measure(steps: tuple[int, ...], width: int = 640, height: int = 360) -> list[dict[str, Any]]:
    """One row per subdivision step: triangles, per-frame ms of both paths (median over
    TIMES, each after a warm-up frame), their stage timings and memory."""
    import tempfile

    from rigspace.runtime.engine import Engine

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for step in steps:
            scene, triangles = heavy_scene(Path(tmp) / f"s{step}", step)
            engines = {
                "mesh": Engine(scene, width=width, height=height, reference=True),
                # The albedo branch's colour at every step: the subdivided meshes' uvs are not
                # the ones the bundle's texture charts were made for (the sampler adds about
                # 19 ms at this size: the texture part).
                "network": Engine(scene, width=width, height=height, textures=False),
            }
            try:
                timings: dict[str, list[dict[str, float]]] = {k: [] for k in engines}
                for engine in engines.values():
                    engine.render(TIMES[0] - 1.0)  # warm-up: sessions, buffers, kernels
                for t in TIMES:
                    for name, engine in engines.items():
                        start = time.perf_counter()
                        frame = engine.render(t)
                        wall = time.perf_counter() - start
                        seconds = frame.report["seconds"]
                        timings[name].append({"wall": wall, **seconds})
                mesh_bytes = _mesh_bytes(engines["mesh"])
                network_bytes = engines["network"].characters[0].model.footprint_bytes()
            finally:
                for engine in engines.values():
                    engine.close()
            rows.append(
                {
                    "step": step,
                    "triangles": triangles,
                    **{
                        f"{name}_ms": 1e3 * statistics.median(r["wall"] for r in records)
                        for name, records in timings.items()
                    },
                    "mesh_scene_ms": 1e3 * statistics.median(r["scene"] for r in timings["mesh"]),
                    "network_stage_ms": 1e3
                    * statistics.median(r["network"] for r in timings["network"]),
                    "mesh_mib": mesh_bytes / 2**20,
                    "network_mib": network_bytes / 2**20,
                }
            )
            shutil.rmtree(Path(tmp) / f"s{step}", ignore_errors=True)
    return rows


def crossover(rows: list[dict[str, Any]]) -> float | None:
    """The triangle count where the mesh path's frame time reaches the network's, by linear
    interpolation in log(triangles) between the first pair of rows that brackets it (None if
    the measured rows never cross)."""
    for low, high in itertools.pairwise(rows):
        d0 = low["mesh_ms"] - low["network_ms"]
        d1 = high["mesh_ms"] - high["network_ms"]
        if d0 <= 0 <= d1 and d1 != d0:
            u = -d0 / (d1 - d0)
            return float(np.exp(np.log(low["triangles"]) * (1 - u) + np.log(high["triangles"]) * u))
    if rows and rows[0]["mesh_ms"] >= rows[0]["network_ms"]:
        return float(rows[0]["triangles"])
    return None


def plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    tris = [r["triangles"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=120)
    ax.plot(tris, [r["mesh_ms"] for r in rows], "o-", label="mesh path (reference render)")
    ax.plot(tris, [r["network_ms"] for r in rows], "s-", label="network path (rigspace render)")
    if result.get("crossover"):
        ax.axvline(result["crossover"], color="grey", ls=":", label="crossover")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("character triangles")
    ax.set_ylabel("ms per 640x360 frame (median)")
    ax.set_title("The premise: mesh cost grows, the network's does not")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

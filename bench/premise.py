"""The paper's premise, measured: a character's mesh path grows with its triangles, the
network's cost does not.

The sample character (22,956 triangles) is subdivided 1 -> 4 triangles per step (edge
midpoints: skin weights, vertex colours and face-varying uvs interpolated, each new point's
four largest joint influences kept and renormalised), giving about 23k, 92k, 367k, 1.5M and
5.9M triangles, each written as a copy of the character that the previs shot references, with
a copy of the sample bundle whose texture charts name the subdivided mesh's uv layout (the
same uvs at the old corners and their midpoints: the same charts, more triangles). Per frame
of the shot at 640x360 (the character about 340 px tall), two engines over the same stage,
one frame of each in turn:

- the mesh path, `reference=True` with the character's rig skinned as a user's CPU path
  skins it (sdk.skinning.CompiledRig: numba LBS over the joints' skinning matrices, blend
  shapes, normals; equal to UsdSkel's skinning), drawn by the renderer as the character's
  layer. Its "posing + skinning + raster" is the frame report's "rig" and "network" stages
  (the reference mode draws the mesh in the stage that otherwise runs the network), its
  "skinning" the bench's own stopwatch around the rig's posed_meshes;
- the network path, as `rigspace render` runs by default: textures on. Its "network" is the
  bench's stopwatch around the bundle's graphs (BundleModel.predict, on the engine's network
  thread), not the frame's "network" stage, which is the wait for that thread after the prims
  were drawn meanwhile.

Memory is the posed mesh's arrays a frame hands the renderer plus what the compiled rig keeps
between frames, against the bundle's graphs. On a GPU the mesh path would skin in a vertex
shader; that path is not built (docs/bench/README.md).
"""

from __future__ import annotations

import itertools
import json
import shutil
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.bench.scenes import PREVIS
from rigspace.sdk.geometry import dense_skin_weights, sparse_skin_weights
from rigspace.sdk.geometry import subdivide_triangles as subdivide

CHARACTER = PREVIS.parent.parent / "character" / "sample_character.usda"
BUNDLE = PREVIS.parent.parent / "models" / "sample"
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
    text = text.replace("@../models/sample@", "@model@")
    scene.write_text(text.replace("@../", f"@{PREVIS.parent.parent}/"))
    _bundle_for(scene, folder / "model")
    return scene, len(triangles)


def _bundle_for(scene: Path, folder: Path) -> None:
    """A copy of the sample bundle in `folder` whose texture charts name the uv layout of the
    scene's (subdivided) character: subdivision keeps every uv at the old corners and puts
    each new one at its edge's uv midpoint, so each new triangle lies inside its parent's uv
    triangle and the charts (their uv boxes and textures) are the bundle's; only the
    fingerprint of the triangle list differs (sdk.texturing.ChartTextures checks it)."""
    from rigspace.sdk import schema
    from rigspace.sdk.charts import uv_fingerprint
    from rigspace.sdk.posing import CharacterRig
    from rigspace.sdk.stage import open_stage

    shutil.copytree(BUNDLE, folder, dirs_exist_ok=True)
    stage = open_stage(scene)
    (prim,) = schema.neural_characters(stage)
    rig = CharacterRig(prim)
    layouts = {
        rig.mesh_name(m): (len(m.triangles), uv_fingerprint(m.triangles, m.corner_uv))
        for m in rig.mesh_sources()
        if m.corner_uv is not None
    }
    charts = folder / "charts.json"
    table = json.loads(charts.read_text())
    for mesh in table["meshes"]:
        mesh["triangles"], mesh["uv_fingerprint"] = layouts[mesh["mesh"]]
    charts.write_text(json.dumps(table))


class Stopwatch:
    """The bench's own timing of a call inside a frame: `watch(obj, "name")` replaces that
    method on `obj` (the instance only) by one that adds its seconds to `seconds`."""

    def __init__(self) -> None:
        self.seconds = 0.0

    def watch(self, obj: object, name: str) -> None:
        call: Callable[..., Any] = getattr(obj, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return call(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start

        setattr(obj, name, timed)

    def lap(self) -> float:
        """The seconds since the last lap, and a new lap."""
        seconds, self.seconds = self.seconds, 0.0
        return seconds


def _mesh_bytes(engine) -> int:
    """What the mesh path holds for a frame: the posed arrays handed to the renderer plus what
    the compiled rig keeps between frames (rest points, influences, triangles, its tables)."""
    total = 0
    for character in engine.characters:
        for mesh in character.rig.posed_meshes(TIMES[0], charts=True):
            total += sum(
                a.nbytes
                for a in (mesh.points, mesh.normals, mesh.triangles, mesh.corner_uv, mesh.chart)
                if a is not None
            )
        total += character.rig.held_bytes()
    return total


def _engines(scene: Path, width: int, height: int) -> tuple[dict[str, Any], dict[str, Stopwatch]]:
    """The two paths' engines over `scene`, and the bench's stopwatches: the mesh path's
    skinning (the compiled rig's posed_meshes) and the network path's graphs."""
    from rigspace.runtime.engine import Engine, EngineSettings
    from rigspace.sdk.skinning import CompiledRig

    mesh = Engine(scene, EngineSettings(width=width, height=height, reference=True))
    network = Engine(
        scene, EngineSettings(width=width, height=height)
    )  # textures on: `rigspace render`
    watches = {"skinning": Stopwatch(), "graphs": Stopwatch()}
    for character in mesh.characters:
        character.rig = CompiledRig(character.prim)
        watches["skinning"].watch(character.rig, "posed_meshes")
    for model in {id(c.model): c.model for c in network.characters}.values():
        watches["graphs"].watch(model, "predict")
    return {"mesh": mesh, "network": network}, watches


def measure(
    steps: tuple[int, ...],
    width: int = 640,
    height: int = 360,
    times: tuple[float, ...] = TIMES,
) -> list[dict[str, Any]]:
    """One row per subdivision step: triangles, per-frame ms of both paths (median over
    `times`, after a warm-up frame each), what each path's time is made of, and memory."""
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for step in steps:
            scene, triangles = heavy_scene(Path(tmp) / f"s{step}", step)
            engines, watches = _engines(scene, width, height)
            try:
                records: dict[str, list[dict[str, Any]]] = {k: [] for k in engines}
                for engine in engines.values():
                    engine.render(times[0] - 1.0)  # warm-up: sessions, buffers, kernels
                for t in times:
                    for name, engine in engines.items():  # one frame of each in turn
                        for watch in watches.values():
                            watch.lap()
                        start = time.perf_counter()
                        frame = engine.render(t)
                        wall = time.perf_counter() - start
                        records[name].append(
                            {
                                "wall": wall,
                                **frame.report.seconds,
                                "skinning": watches["skinning"].lap(),
                                "graphs": watches["graphs"].lap(),
                                "entries": frame.report.characters,
                            }
                        )
                mesh_bytes = _mesh_bytes(engines["mesh"])
                network_bytes = engines["network"].characters[0].model.footprint_bytes()
            finally:
                for engine in engines.values():
                    engine.close()
            rows.append(_row(step, triangles, records, mesh_bytes, network_bytes))
            shutil.rmtree(Path(tmp) / f"s{step}", ignore_errors=True)
    return rows


def _row(
    step: int,
    triangles: int,
    records: dict[str, list[dict[str, Any]]],
    mesh_bytes: int,
    network_bytes: int,
) -> dict[str, Any]:
    def ms(path: str, value: Callable[[dict[str, Any]], float]) -> float:
        return 1e3 * statistics.median(value(r) for r in records[path])

    last = records["network"][-1]["entries"][0]
    return {
        "step": step,
        "triangles": triangles,
        "mesh_ms": ms("mesh", lambda r: r["wall"]),
        # The reference mode draws the skinned mesh in the "network" stage; "rig" poses the
        # joints (the same in both modes).
        "mesh_pose_raster_ms": ms("mesh", lambda r: r["rig"] + r["network"]),
        "mesh_skinning_ms": ms("mesh", lambda r: r["skinning"]),
        "network_ms": ms("network", lambda r: r["wall"]),
        "network_graphs_ms": ms("network", lambda r: r["graphs"]),
        "network_wait_ms": ms("network", lambda r: r["network"]),
        "network_texture_ms": ms(
            "network", lambda r: sum(e.get("texture_ms", 0.0) for e in r["entries"]) / 1e3
        ),
        "network_colour": last.get("colour", last.get("reason", "")),
        "mesh_mib": mesh_bytes / 2**20,
        "network_mib": network_bytes / 2**20,
    }


def crossover(rows: list[dict[str, Any]]) -> float | None:
    """The triangle count where the mesh path's frame time comes up to the network's: linear
    interpolation in log(triangles) between the first pair of neighbouring rows whose mesh
    path goes from below the network's to at or above it. None when no such pair is among the
    rows (the rows do not cross: either path cheaper at every measured size)."""
    for low, high in itertools.pairwise(rows):
        d0 = low["mesh_ms"] - low["network_ms"]
        d1 = high["mesh_ms"] - high["network_ms"]
        if d0 < 0 <= d1:
            u = -d0 / (d1 - d0)
            return float(np.exp(np.log(low["triangles"]) * (1 - u) + np.log(high["triangles"]) * u))
    return None


def crossover_sentence(rows: list[dict[str, Any]]) -> str:
    """What the rows say about the crossover, in the report's words (from the rows alone)."""
    if not rows:
        return "No rows were measured."

    def ratio(row: dict[str, Any]) -> str:
        return f"{row['mesh_ms'] / row['network_ms']:.1f}x the network's at {row['triangles']:,}"

    first, last = rows[0], rows[-1]
    cross = crossover(rows)
    if cross is not None:
        return (
            f"The mesh path comes up to the network's frame time at about {cross:,.0f} "
            f"triangles (interpolated in log triangles between the rows around it); it takes "
            f"{ratio(last)}."
        )
    if all(r["mesh_ms"] >= r["network_ms"] for r in rows):
        return (
            f"The rows do not cross: the mesh path costs more than the network at every "
            f"measured size, from {ratio(first)} triangles to {ratio(last)}."
        )
    if all(r["mesh_ms"] < r["network_ms"] for r in rows):
        return (
            f"The rows do not cross: the mesh path costs less than the network at every "
            f"measured size ({ratio(first)} triangles, {ratio(last)})."
        )
    return (
        f"The rows do not cross from below: the mesh path starts above the network's ("
        f"{ratio(first)} triangles) and ends at {ratio(last)}."
    )


def plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    tris = [r["triangles"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=120)
    ax.plot(tris, [r["mesh_ms"] for r in rows], "o-", label="mesh path (compiled skinning, raster)")
    ax.plot(tris, [r["network_ms"] for r in rows], "s-", label="network path (rigspace render)")
    cross = crossover(rows)
    if cross is not None:
        ax.axvline(cross, color="grey", ls=":", label="crossover")
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

"""Renders per second of each usable renderer on a deforming, textured ~20k-triangle mesh."""

from __future__ import annotations

import argparse
import time

import numpy as np

from rigspace.sdk.camera import Camera
from rigspace.sdk.render import DrawMesh, RenderSettings, renderer_plugins


def textured_sphere(rings: int = 100, segments: int = 100) -> DrawMesh:
    """A UV sphere of 2 * rings * segments triangles with faceVarying st and a checker texture."""
    theta = np.linspace(0.0, np.pi, rings + 1)[:, None]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :]
    points = np.stack(
        np.broadcast_arrays(
            np.sin(theta) * np.cos(phi), np.cos(theta), -np.sin(theta) * np.sin(phi)
        ),
        axis=-1,
    ).reshape(-1, 3)
    i, j = np.mgrid[:rings, :segments]
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    triangles = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)
    # st from the unwrapped grid, so the seam column gets u = 1 rather than wrapping to 0.
    su, sv = j / segments, 1 - i / rings
    du, dv = 1 / segments, 1 / rings
    uv_a, uv_b = np.stack([su, sv], -1), np.stack([su + du, sv], -1)
    uv_c, uv_d = np.stack([su, sv - dv], -1), np.stack([su + du, sv - dv], -1)
    corner_uv = np.concatenate(
        [np.stack([uv_a, uv_c, uv_b], -2), np.stack([uv_b, uv_c, uv_d], -2)]
    ).reshape(-1, 3, 2)
    checker = (np.add.outer(np.arange(64) // 8, np.arange(64) // 8) % 2)[..., None]
    texture = np.where(checker, (0.8, 0.6, 0.2), (0.1, 0.2, 0.5))
    return DrawMesh(
        points.astype(np.float32),
        triangles.astype(np.int32),
        corner_uv=corner_uv.astype(np.float32),
        texture=texture.astype(np.float32),
        name="bench_sphere",
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=60, help="frames per renderer and size")
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256], help="square sizes")
    parser.add_argument("--samples-per-axis", type=int, default=2)
    args = parser.parse_args(argv)

    mesh = textured_sphere()
    rest = mesh.points.copy()
    settings = RenderSettings(args.samples_per_axis)
    plugins = renderer_plugins()
    renderers = {}
    for spec in plugins:
        reason = spec.unavailable()
        if reason is None:
            renderers[spec.name] = spec.create(settings)
        else:
            print(f"{spec.name}: unavailable ({reason})")
    print(f"{len(mesh.triangles)} triangles, {settings.samples_per_axis}^2 samples per pixel")
    for size in args.sizes:
        cam = Camera.look_at(
            (0.0, 0.5, 3.0), (0.0, 0.0, 0.0), width=size, height=size, focal_length=35.0,
            horizontal_aperture=20.955,
        )  # fmt: skip
        seconds = dict.fromkeys(renderers, 0.0)
        for renderer in renderers.values():
            renderer.render([mesh], cam)  # warm up: context, shaders, caches
        # Interleave the renderers frame by frame so machine noise hits them alike.
        for frame in range(args.frames):
            bump = 1 + 0.1 * np.sin(4 * rest[:, 1] + 0.3 * frame)
            mesh.points = (rest * bump[:, None]).astype(np.float32)  # deforms every frame
            for name, renderer in renderers.items():
                start = time.perf_counter()
                renderer.render([mesh], cam)
                seconds[name] += time.perf_counter() - start
        for name, total in seconds.items():
            print(f"{name:8s} {size}x{size}: {args.frames / total:6.1f} renders/s")
    for renderer in renderers.values():
        renderer.close()


if __name__ == "__main__":
    main()

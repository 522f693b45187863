"""Capsule shadows in a fragment shader: shadows.capsule_visibility's maths, one pixel per receiver."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from rigspace.runtime.lights import DISTANT, Light
from rigspace.sdk.render.gl import FULL_SCREEN_VERTEX_SHADER, SharedContext, share

MAX_CAPSULES = 64
"""Capsules per draw; more are drawn in batches whose visibilities multiply. Each count gets
its own program, its loop bound a constant (llvmpipe unrolls it: measured faster than a loop
to a uniform count)."""
ROW = 1024
"""Receivers per row of the points texture (a frame's candidates fill a few rows)."""


_FRAGMENT = """
#version 330 core
#define COUNT %(count)d
#define GROUPS %(groups)d
uniform sampler2D points;   // RGB32F world positions, one texel per receiver
uniform vec4 bound[GROUPS]; // a sphere (centre, radius) around each group of capsules (a limb)
uniform int last[GROUPS];   // one past the group's last capsule
uniform vec3 start[COUNT];  // segment starts a
uniform vec3 along[COUNT];  // b - a
uniform float radius[COUNT];
uniform bool is_point;
uniform vec3 towards;              // a DistantLight: unit direction towards it
uniform float angle;               // its angular radius
uniform vec3 position;             // a point light: its position and soft radius
uniform float soft;
out float visibility;
const float PI = 3.14159265358979;
const float MIN_VISIBILITY = %(min_visibility)g;

// Inverse cosines and sines by atan: Mesa's asin and acos approximations are off by
// up to 3e-4 of the occlusion, its atan is not.
float arccos(float x) {
    return atan(sqrt(max(1.0 - x * x, 0.0)), x);
}

// shadows.cone_occlusion: the overlap of two discs (radii r1, r2, centres d apart) over
// the first's area.
float cone_occlusion(float r1, float r2, float d) {
    float ds = max(d, 1e-9);
    float c1 = clamp((d * d + r1 * r1 - r2 * r2) / (2.0 * ds * r1), -1.0, 1.0);
    float c2 = clamp((d * d + r2 * r2 - r1 * r1) / (2.0 * ds * max(r2, 1e-9)), -1.0, 1.0);
    float kite = sqrt(max((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2), 0.0));
    float lens = r1 * r1 * arccos(c1) + r2 * r2 * arccos(c2) - 0.5 * kite;
    float inner = min(r1, r2) * min(r1, r2);
    float area = d >= r1 + r2 ? 0.0 : (d <= abs(r1 - r2) ? PI * inner : lens);
    return clamp(area / (PI * r1 * r1), 0.0, 1.0);
}

// Whether a sphere's cone (centre c from the receiver, radius r) surely misses the
// light's (towards d), with no inverse sines: the angle between them is below
// light_angle + sphere_angle only where the centre lies within distance * sin(light_angle)
// + r of the ray (and, behind the receiver, only where r > -ahead * cos(light_angle)).
bool misses(vec3 c, float r, vec3 d, float sin_light, float cos_light) {
    float ahead = dot(c, d);
    vec3 off = c - ahead * d;
    float reach = length(c) * sin_light + r;
    return ahead <= 0.0 ? r < -ahead * cos_light : dot(off, off) >= reach * reach;
}

void main() {
    vec3 p = texelFetch(points, ivec2(gl_FragCoord.xy), 0).xyz;
    vec3 d = towards;
    float light_angle = angle;
    if (is_point) {
        vec3 offset = position - p;
        float distance = max(length(offset), 1e-6);
        d = offset / distance;
        light_angle = soft >= distance ? PI / 2.0 : atan(soft, sqrt(distance * distance - soft * soft));
    }
    float sin_light = sin(light_angle), cos_light = cos(light_angle);
    float log_visibility = 0.0;
    int first = 0;
    for (int g = 0; g < GROUPS; ++g) {
      int end = last[g];
      // A limb whose bounding sphere misses the light hides none of it (its capsules lie
      // inside, so their cones do too; a receiver inside the sphere is never skipped).
      if (!misses(bound[g].xyz - p, bound[g].w, d, sin_light, cos_light)) {
      for (int k = first; k < end; ++k) {
        vec3 u = along[k];
        vec3 w0 = start[k] - p;
        float uu = dot(u, u), ud = dot(u, d), uw = dot(u, w0), dw = dot(d, w0);
        float denominator = uu - ud * ud;
        float s = denominator > 1e-9 ? (ud * dw - uw) / max(denominator, 1e-9) : 0.0;
        vec3 c = w0 + clamp(s, 0.0, 1.0) * u;
        float r = radius[k];
        if (misses(c, r, d, sin_light, cos_light)) continue;
        float distance = max(length(c), 1e-6);
        if (distance <= r) continue;  // a receiver inside: not its caster
        float sphere_angle = atan(r, sqrt(max(distance * distance - r * r, 0.0)));
        float between = atan(length(cross(c, d)), dot(c, d));
        if (between >= light_angle + sphere_angle) continue;  // no overlap: log(1)
        float occlusion = cone_occlusion(light_angle, sphere_angle, between);
        log_visibility += log(max(1.0 - occlusion, MIN_VISIBILITY));
      }
      }
      first = end;
    }
    visibility = exp(log_visibility);
}
"""


def _batches(groups: Sequence[np.ndarray]) -> list[list[np.ndarray]]:
    """Groups packed into draws of at most MAX_CAPSULES capsules (a longer group split)."""
    pieces = [g[i : i + MAX_CAPSULES] for g in groups for i in range(0, len(g), MAX_CAPSULES)]
    out: list[list[np.ndarray]] = [[]]
    for piece in pieces:
        if sum(len(g) for g in out[-1]) + len(piece) > MAX_CAPSULES:
            out.append([])
        out[-1].append(piece)
    return [batch for batch in out if batch]


def _spheres(a: np.ndarray, b: np.ndarray, radius: np.ndarray, groups) -> np.ndarray:
    """(G, 4) float32 spheres (centre, radius) holding each group's capsules."""
    out = np.zeros((len(groups), 4), np.float32)
    for j, g in enumerate(groups):
        ends = np.concatenate([a[g], b[g]])
        centre = (ends.min(axis=0) + ends.max(axis=0)) / 2
        reach = np.linalg.norm(ends - centre, axis=1) + np.concatenate([radius[g]] * 2)
        out[j, :3], out[j, 3] = centre, reach.max() * 1.001 + 1e-4
    return out


class GLCapsuleShadows:
    """The capsule programs in an EGL context (shared with the engine's renderer, or its
    own); textures grow with the largest batch of receivers seen."""

    def __init__(self, min_visibility: float, shared: SharedContext | None = None) -> None:
        self._shared = share(shared)
        self._ctx = self._shared.acquire()
        with self._ctx:
            self.renderer = str(self._ctx.info["GL_RENDERER"])
        """What draws: a GPU's name, or Mesa's "llvmpipe (LLVM ...)" on the CPU."""
        self._floor = min_visibility
        self._programs: dict[tuple[int, int], tuple[Any, Any]] = {}
        """Per (capsules, groups) count, a program and its vertex array."""
        self._rows = 0
        self._points: Any = None
        self._target: Any = None
        self._fbo: Any = None

    def _grow(self, rows: int) -> None:
        if rows <= self._rows:
            return
        self._release_targets()
        rows = max(rows, 2 * self._rows)
        self._points = self._ctx.texture((ROW, rows), 3, dtype="f4")
        self._target = self._ctx.texture((ROW, rows), 1, dtype="f4")
        self._fbo = self._ctx.framebuffer(color_attachments=[self._target])
        self._rows = rows

    def visibility(
        self,
        points: np.ndarray,
        a: np.ndarray,
        b: np.ndarray,
        radius: np.ndarray,
        groups: Sequence[np.ndarray],
        light: Light,
        angle: float,
        soft: float,
    ) -> np.ndarray:
        """(N,) how much of `light` reaches planar (3, N) float32 `points` past capsules
        (K, 3) a-b of `radius`, tested group by group (index arrays, a limb each; empty:
        one group): the light's angular radius `angle` for a DistantLight, a point light's
        `soft` radius (shadows._soft_radius)."""
        with self._ctx:
            return self._visibility(points, a, b, radius, groups, light, angle, soft)

    def _program(self, count: int, groups: int) -> tuple[Any, Any]:
        if (count, groups) not in self._programs:
            source = _FRAGMENT % {
                "count": count, "groups": groups, "min_visibility": self._floor
            }  # fmt: skip
            program = self._ctx.program(
                vertex_shader=FULL_SCREEN_VERTEX_SHADER, fragment_shader=source
            )
            self._programs[count, groups] = (program, self._ctx.vertex_array(program, []))
        return self._programs[count, groups]

    def _visibility(self, points, a, b, radius, groups, light, angle, soft) -> np.ndarray:
        n = points.shape[1]
        if n == 0:
            return np.ones(0, np.float32)
        width = min(n, ROW)
        rows = -(-n // width)
        self._grow(rows)
        packed = np.zeros((rows * width, 3), np.float32)
        packed[:n] = points.T
        self._points.write(packed.tobytes(), viewport=(0, 0, width, rows))
        self._points.use(0)
        self._fbo.use()
        self._fbo.viewport = (0, 0, width, rows)
        out = np.ones(n, np.float32)
        for batch in _batches(groups or (np.arange(len(radius)),)):
            order = np.concatenate(batch)
            program, vao = self._program(len(order), len(batch))
            program["points"].value = 0
            program["is_point"].value = light.kind != DISTANT
            program["towards"].value = tuple(-light.direction.astype(np.float64))
            program["angle"].value = float(angle)
            program["position"].value = tuple(light.position.astype(np.float64))
            program["soft"].value = float(soft)
            program["start"].write(a[order].astype(np.float32).tobytes())
            program["along"].write((b[order] - a[order]).astype(np.float32).tobytes())
            program["radius"].write(radius[order].astype(np.float32).tobytes())
            program["bound"].write(_spheres(a, b, radius, batch).tobytes())
            program["last"].write(np.cumsum([len(g) for g in batch]).astype(np.int32).tobytes())
            vao.render(vertices=3)
            data = self._fbo.read(viewport=(0, 0, width, rows), components=1, dtype="f4")
            out *= np.frombuffer(data, np.float32)[:n]
        return out

    def _release_targets(self) -> None:
        for thing in (self._fbo, self._target, self._points):
            if thing is not None:
                thing.release()
        self._fbo = self._target = self._points = None
        self._rows = 0

    def close(self) -> None:
        with self._ctx:
            self._release_targets()
            for program, vao in self._programs.values():
                vao.release()
                program.release()
            self._programs = {}
        self._shared.release()

"""Embree 4 through ctypes: triangle scenes over shared numpy buffers and packets of 16 rays.

embreex (the embree renderer's dependency) ships the Embree 4 library; its Python wrapper
copies a mesh's vertices and indices one element at a time, about a second per million
triangles, which made each captured pose of a film-weight character cost more than its 32
views' rays. Here the scene reads the numpy buffers in place (rtcSetSharedGeometryBuffer), so
building one is Embree's BVH build alone, and rays go 16 to a call (rtcIntersect16).

Only the few calls the renderer needs are bound; the struct layouts are Embree 4's
(rtcore_ray.h). Every pointer handed to Embree is kept alive by the object that uses it.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os
from collections.abc import Sequence

import numpy as np

GEOMETRY_TRIANGLE = 0
BUFFER_INDEX, BUFFER_VERTEX = 0, 1
FORMAT_UINT3, FORMAT_FLOAT3 = 0x5003, 0x9003
INVALID_ID = 0xFFFFFFFF
PACKET = 16
"""Rays a call: rtcIntersect16 (AVX-512's width; narrower CPUs run it in halves or quarters)."""

# RTCRayHit16, structure of arrays: 12 ray fields then the hit's (Ng x3, u, v, primID,
# geomID, instID, instPrimID), each 16 wide. The stride leaves room for every Embree 4 build.
_RAY_FIELDS = (
    "org_x", "org_y", "org_z", "tnear", "dir_x", "dir_y", "dir_z", "time",
    "tfar", "mask", "id", "flags",
    "Ng_x", "Ng_y", "Ng_z", "u", "v", "primID", "geomID", "instID", "instPrimID",
)  # fmt: skip
_UINT_FIELDS = {"mask", "id", "flags", "primID", "geomID", "instID", "instPrimID"}
PACKET_DTYPE = np.dtype(
    {
        "names": list(_RAY_FIELDS),
        "formats": [("<u4" if f in _UINT_FIELDS else "<f4", (PACKET,)) for f in _RAY_FIELDS],
        "offsets": [i * PACKET * 4 for i in range(len(_RAY_FIELDS))],
        "itemsize": 1408,  # 21 fields of 64 bytes, rounded up to the 64-byte alignment
    }
)


def library_path() -> str:
    """The Embree 4 shared library: the one embreex's wheel ships, else the system's."""
    import embreex

    here = os.path.dirname(embreex.__file__)
    found = sorted(glob.glob(os.path.join(here, os.pardir, "embreex.libs", "libembree4*.so*")))
    found += sorted(glob.glob(os.path.join(here, ".dylibs", "libembree4*.dylib")))
    if found:
        return found[0]
    import ctypes.util

    system = ctypes.util.find_library("embree4")
    if system is None:
        raise OSError("no Embree 4 library beside embreex or on the system")
    return system


@functools.cache
def _lib() -> ctypes.CDLL:
    lib = ctypes.CDLL(library_path())
    p, u, i, sz = ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t
    signatures = {
        "rtcNewDevice": (p, [ctypes.c_char_p]),
        "rtcReleaseDevice": (None, [p]),
        "rtcGetDeviceError": (i, [p]),
        "rtcNewScene": (p, [p]),
        "rtcReleaseScene": (None, [p]),
        "rtcCommitScene": (None, [p]),
        "rtcNewGeometry": (p, [p, i]),
        "rtcReleaseGeometry": (None, [p]),
        "rtcCommitGeometry": (None, [p]),
        "rtcAttachGeometry": (u, [p, p]),
        "rtcSetSharedGeometryBuffer": (None, [p, i, u, i, p, sz, sz, sz]),
        "rtcIntersect16": (None, [p, p, p, p]),
    }
    for name, (restype, argtypes) in signatures.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = restype, argtypes
    return lib


class Device:
    """One Embree device (its thread pool), shared by every scene of a renderer."""

    def __init__(self) -> None:
        self._lib = _lib()
        self.handle = self._lib.rtcNewDevice(None)
        if not self.handle:
            raise OSError("Embree could not create a device (rtcNewDevice returned NULL)")

    def check(self, what: str) -> None:
        code = self._lib.rtcGetDeviceError(self.handle)
        if code:
            raise RuntimeError(f"Embree failed to {what} (RTCError {code})")

    def close(self) -> None:
        if self.handle:
            self._lib.rtcReleaseDevice(self.handle)
            self.handle = None


class TriangleScene:
    """Triangle meshes numbered 0, 1, ... (geomID) over shared numpy buffers, committed."""

    def __init__(self, device: Device, meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> None:
        self._lib, self._device = device._lib, device
        self._buffers: list[np.ndarray] = []  # Embree reads these in place: keep them alive
        self.handle = self._lib.rtcNewScene(device.handle)
        for points, triangles in meshes:
            # Embree reads a vertex buffer's last element with a 16-byte load: one padding row.
            vertices = np.zeros((len(points) + 1, 3), np.float32)
            vertices[:-1] = points
            index = np.ascontiguousarray(triangles, dtype=np.uint32)
            geometry = self._lib.rtcNewGeometry(device.handle, GEOMETRY_TRIANGLE)
            self._share(geometry, BUFFER_VERTEX, FORMAT_FLOAT3, vertices, len(points))
            self._share(geometry, BUFFER_INDEX, FORMAT_UINT3, index, len(index))
            self._lib.rtcCommitGeometry(geometry)
            self._lib.rtcAttachGeometry(self.handle, geometry)
            self._lib.rtcReleaseGeometry(geometry)  # the scene holds it now
            self._buffers += [vertices, index]
        self._lib.rtcCommitScene(self.handle)
        device.check("build a scene")

    def _share(self, geometry: int, kind: int, fmt: int, array: np.ndarray, count: int) -> None:
        self._lib.rtcSetSharedGeometryBuffer(
            geometry, kind, 0, fmt, array.ctypes.data, 0, 12, count
        )

    def intersect(self, origins: np.ndarray, directions: np.ndarray, far: np.ndarray) -> dict:
        """The first hit of each ray from `origins` along `directions` (N,3), within [0, far]:
        a dict of (N,) arrays tfar, u, v, primID, geomID (-1 where nothing is hit), as embreex's
        `run(..., output=1)` gives them (p = (1 - u - v) p0 + u p1 + v p2)."""
        n = len(origins)
        packets = -(-n // PACKET)
        # 64-byte aligned packets: over-allocate and start at the first aligned byte.
        raw = np.zeros(packets * PACKET_DTYPE.itemsize + 64, np.uint8)
        start = -raw.ctypes.data % 64
        rays = raw[start : start + packets * PACKET_DTYPE.itemsize].view(PACKET_DTYPE)
        lanes = packets * PACKET

        def put(field: str, values: np.ndarray | int) -> None:
            column = np.zeros(lanes, rays.dtype[field].base)
            column[:n] = values
            rays[field] = column.reshape(packets, PACKET)  # a field of packets is strided

        for axis, name in enumerate("xyz"):
            put(f"org_{name}", origins[:, axis])
            put(f"dir_{name}", directions[:, axis])
        put("tfar", far)
        for field in ("mask", "geomID", "instID"):  # every ray sees every geometry; no hit yet
            rays[field] = INVALID_ID
        valid = np.zeros(lanes, np.int32)
        valid[:n] = -1
        intersect, scene = self._lib.rtcIntersect16, self.handle
        base, stride = rays.ctypes.data, PACKET_DTYPE.itemsize
        valid_base = valid.ctypes.data
        for k in range(packets):
            intersect(valid_base + 64 * k, scene, base + stride * k, None)
        self._device.check("intersect rays")

        def got(field: str) -> np.ndarray:
            return rays[field].reshape(-1)[:n]  # a copy: the fields are strided

        return {
            "tfar": got("tfar"),
            "u": got("u"),
            "v": got("v"),
            "primID": got("primID").view(np.int32),
            "geomID": got("geomID").view(np.int32),
        }

    def close(self) -> None:
        if self.handle:
            self._lib.rtcReleaseScene(self.handle)
            self.handle = None
            self._buffers = []

    def __del__(self) -> None:
        self.close()

"""Built-in live sources, chosen by URL scheme through the `rigspace.sources` plugin kind."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from rigspace.runtime.live.decoders.bvh import BvhError, BvhStreamDecoder, read_bvh
from rigspace.runtime.live.decoders.evdev import (
    DEFAULT_AXES,
    EvdevDecoder,
    parse_axes,
    parse_clips,
)
from rigspace.runtime.live.decoders.vmc import VmcDecoder
from rigspace.runtime.live.decoders.ximu3 import Ximu3Decoder
from rigspace.runtime.live.transports import (
    DeviceFileSource,
    LiveSourceError,
    ReplaySource,
    SerialSource,
    Source,
    TcpClientSource,
    UdpSource,
)
from rigspace.sdk.plugins import SOURCES, SourceSpec, discover

VMC_PORT = 39539
"""The VMC protocol's default receiver (Marionette) port."""
AXIS_NEURON_BVH_PORT = 7001
"""Axis Neuron's default BVH data-stream port."""
DEFAULT_HOST = "127.0.0.1"
EXPECTS = {
    "axes": "CONTROL:JOINT:AXIS:DEGREES[:MIN:MAX],... (such as ABS_RX:head:Y:-60)",
    "clips": "CONTROL:CLIP[:MIN:MAX],... (such as ABS_RZ:wave or BTN_SOUTH:wave)",
    "speed": "positive number",
    "retry": "positive number of seconds",
    "loop": "0, 1, true or false",
    "baud": "whole number",
    "baudrate": "whole number",
}
"""What an option's value looks like, for the error that names a bad one."""


def _label(url: str, name: str) -> str:
    return f"Live source {name!r} ({url})" if name else f"Live source {url}"


def _options(url: str, name: str, query: str, allowed: dict[str, Callable[[str], Any]]) -> dict:
    """URL query -> typed options; an unknown key or a bad value names the URL and the fix."""
    options: dict[str, Any] = {}
    for key, value in parse_qsl(query, keep_blank_values=True):
        if key not in allowed:
            raise LiveSourceError(
                f"{_label(url, name)}: unknown option {key!r}.",
                f"use only {', '.join(sorted(allowed)) or 'no options'} in the URL query.",
            )
        try:
            options[key] = allowed[key](value)
        except ValueError:
            raise LiveSourceError(
                f"{_label(url, name)}: option {key}={value!r} is not valid.",
                f"{key} takes a {EXPECTS.get(key, allowed[key].__name__)}.",
            ) from None
    return options


def _host_port(url: str, name: str, default_port: int) -> tuple[str, int, str]:
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        raise LiveSourceError(
            f"{_label(url, name)}: the port is not a number from 0 to 65535.",
            "write scheme://HOST:PORT, such as vmc://127.0.0.1:39539.",
        ) from None
    return parts.hostname or DEFAULT_HOST, default_port if port is None else port, parts.query


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise ValueError(text)
    return value


def _flag(text: str) -> bool:
    if text not in ("0", "1", "true", "false"):
        raise ValueError(text)
    return text in ("1", "true")


def open_vmc(url: str, name: str = "") -> Source:
    """vmc://HOST:PORT: the VMC protocol over UDP (OSC), Unity HumanBodyBones."""
    host, port, query = _host_port(url, name, VMC_PORT)
    _options(url, name, query, {})
    return UdpSource(name, url, VmcDecoder(), host, port)


def _skeleton(url: str, name: str, path: str) -> Any:
    try:
        return read_bvh(path)
    except BvhError as exc:
        raise LiveSourceError(f"{_label(url, name)}: {exc.what}", exc.fix) from None


def open_bvh_tcp(url: str, name: str = "") -> Source:
    """bvh+tcp://HOST:PORT?skeleton=FILE.bvh: the Axis Neuron BVH data stream (TCP client)."""
    host, port, query = _host_port(url, name, AXIS_NEURON_BVH_PORT)
    options = _options(url, name, query, {"skeleton": str, "retry": _positive})
    if "skeleton" not in options:
        raise LiveSourceError(
            f"{_label(url, name)}: the stream's hierarchy is not given.",
            "add ?skeleton=FILE.bvh (a BVH file with the sender's HIERARCHY) to the URL.",
        )
    skeleton = _skeleton(url, name, options["skeleton"])[0]
    return TcpClientSource(
        name, url, BvhStreamDecoder(skeleton), host, port, options.get("retry", 0.5)
    )


def _after_scheme(url: str) -> tuple[str, str]:
    """The text between scheme:// and the first '?', and the query."""
    rest = url.split("://", 1)[1]
    target, _, query = rest.partition("?")
    return target, query


def open_serial(url: str, name: str = "") -> Source:
    """serial://DEVICE[,DEVICE...]?baud=N&format=ximu3&bones=B1[,B2...]: x-IMU3 orientation
    messages from pyserial ports (a path, or any pyserial URL such as loop://), one sensor each."""
    target, query = _after_scheme(url)
    options = _options(
        url, name, query, {"baud": int, "baudrate": int, "format": str, "bones": str}
    )
    devices = [d for d in target.split(",") if d]
    if not devices:
        raise LiveSourceError(
            f"{_label(url, name)}: no serial device.",
            "write serial://DEVICE?format=ximu3, such as serial:///dev/ttyACM0?format=ximu3.",
        )
    fmt = options.get("format", "ximu3")
    if fmt != "ximu3":
        raise LiveSourceError(
            f"{_label(url, name)}: serial format {fmt!r} is not known.", "use format=ximu3."
        )
    bones = tuple(b for b in options.get("bones", "").split(",") if b) or tuple(
        f"sensor{i}" for i in range(len(devices))
    )
    if len(bones) != len(devices):
        raise LiveSourceError(
            f"{_label(url, name)}: {len(devices)} devices but {len(bones)} bones.",
            "name one bone per device in bones=B1,B2,... (same order as the devices).",
        )
    baud = options.get("baud", options.get("baudrate", 115200))
    return SerialSource(name, url, Ximu3Decoder(bones), devices, baud)


def open_replay(url: str, name: str = "") -> Source:
    """replay://PATH?speed=1&loop=1: plays a BVH file or a recorded take (.usd, .usda, .usdc)
    in real time (replay:///abs or replay://relative/path)."""
    target, query = _after_scheme(url)
    options = _options(url, name, query, {"speed": _positive, "loop": _flag})
    if not target:
        raise LiveSourceError(
            f"{_label(url, name)}: no file.", "write replay://PATH.bvh?speed=1&loop=1."
        )
    path = Path(target)
    speed, loop = options.get("speed", 1.0), options.get("loop", True)
    suffix = path.suffix.lower()
    if suffix in (".usd", ".usda", ".usdc"):
        from rigspace.runtime.live.record import TakeError, read_take

        try:
            take = read_take(path)
        except TakeError as exc:
            raise LiveSourceError(f"{_label(url, name)}: {exc.what}", exc.fix) from None
        blend = None if take.blend_weights is None else (take.blend_shapes, take.blend_weights)
        return ReplaySource(
            name, url, take.bones, take.rotations, take.root_positions, take.times, speed, loop,
            take.parents, take.meters_per_unit, native=True, blend=blend,
        )  # fmt: skip
    if suffix != ".bvh":
        raise LiveSourceError(
            f"{_label(url, name)}: {path} is neither a .bvh file nor a recorded take.",
            "replay a BVH file or a take written by rigspace (.usd, .usda, .usdc).",
        )
    skeleton, motion, frame_time = _skeleton(url, name, target)
    if len(motion) == 0:
        raise LiveSourceError(
            f"{_label(url, name)}: {path} has no MOTION frames.", "replay a BVH file with motion."
        )
    rotations, roots = skeleton.pose(motion)
    return ReplaySource(
        name, url, skeleton.names, rotations, roots, np.arange(len(motion)) * frame_time, speed,
        loop, skeleton.parents, rest_positions=skeleton.rest_positions(),
    )  # fmt: skip


def open_gamepad(url: str, name: str = "") -> Source:
    """gamepad://[DEVICE]?axes=CONTROL:JOINT:AXIS:DEGREES[:MIN:MAX],...&clips=CONTROL:CLIP,...
    &shapes=CONTROL:SHAPE,...: a Linux evdev game controller whose axes and buttons turn joints
    on top of the stage animation (default: right stick head yaw/pitch, left stick spine lean),
    blend towards the stage's clips and set blend shape weights (the binding's
    gamepadOffsets/gamepadClips/gamepadShapes arrive as these options).
    No DEVICE: the first /dev/input/by-id joystick."""
    import glob

    target, query = _after_scheme(url)
    options = _options(
        url, name, query, {"axes": parse_axes, "clips": parse_clips, "shapes": parse_clips}
    )
    device = target
    if not device:
        found = sorted(glob.glob("/dev/input/by-id/*-event-joystick"))
        if not found:
            raise LiveSourceError(
                f"{_label(url, name)}: no game controller is connected.",
                "plug one in (it appears in /dev/input/by-id), or name its device: "
                "gamepad:///dev/input/eventN.",
            )
        device = found[0]
    decoder = EvdevDecoder(
        options.get("axes", DEFAULT_AXES), options.get("clips", ()), options.get("shapes", ())
    )
    return DeviceFileSource(name, url, decoder, device)


VMC = SourceSpec(
    "vmc", open_vmc, "vmc://HOST:PORT  VMC protocol (OSC over UDP), default port 39539"
)
BVH_TCP = SourceSpec(
    "bvh+tcp",
    open_bvh_tcp,
    "bvh+tcp://HOST:PORT?skeleton=FILE.bvh  Axis Neuron BVH data stream (TCP, reconnects)",
)
SERIAL = SourceSpec(
    "serial",
    open_serial,
    "serial://DEVICE[,DEVICE]?baud=115200&format=ximu3&bones=B1[,B2]  x-IMU3 over pyserial",
)
GAMEPAD = SourceSpec(
    "gamepad",
    open_gamepad,
    "gamepad://[DEVICE]?axes=ABS_RX:head:Y:-60,...&clips=ABS_RZ:wave  a Linux evdev controller: "
    "additive offsets, clip blends",
)
REPLAY = SourceSpec(
    "replay", open_replay, "replay://PATH?speed=1&loop=1  a BVH file or recorded take, in real time"
)


def open_source(
    url: str, name: str = "", extra: dict[str, Callable[[], Any]] | None = None
) -> Source:
    """Open the source `url` names (not started) for the binding called `name`."""
    scheme = url.split("://", 1)[0].lower() if "://" in url else ""
    found = discover(SOURCES, extra)
    specs = {spec.scheme: spec for spec in found}
    if scheme in specs:
        return specs[scheme].factory(url, name)
    if scheme in found.failed:  # plugins are named after their scheme
        raise LiveSourceError(
            f"{_label(url, name)}: the {scheme!r} source plugin failed to load: "
            f"{found.failed[scheme]}",
            "install what the error names, or use another source.",
        )
    known = ", ".join(f"{s}://" for s in sorted(specs)) or "(none installed)"
    raise LiveSourceError(
        f"{_label(url, name)}: no live source handles "
        + (f"the scheme {scheme!r}." if scheme else "a URL without scheme://."),
        f"use one of {known}, or install the plugin that provides it.",
    )

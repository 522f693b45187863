"""`rigspace view`: serve the browser inspector for one scene on a local port."""

from __future__ import annotations

import argparse
import socket
import sys
import threading
import time
import webbrowser
from typing import TYPE_CHECKING

from rigspace.runtime.options import (
    add_regions_argument,
    add_source_argument,
    add_view_arguments,
)
from rigspace.sdk.cli import CommandSpec
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.predictors import add_predictor_argument

if TYPE_CHECKING:  # the Engine, USD and uvicorn load when the command runs, not at --help
    import uvicorn

    from rigspace.runtime.view.server import Viewer


DESCRIPTION = """\
A usdview-style inspector in the browser: the prim tree, the selected prim's properties at
the current time (authored or fallback, time samples, relationship targets, metadata, a
neural character's bundle and metrics), the layer stack and its composition, validation
findings linked to their prims, a timeline with a camera picker, and a viewport with the
Engine's frame (beauty, albedo, normal, depth, mask), each character's billboard, level,
decision and cost (and its regions': the face, a hand), a frame-time graph, and the live
bindings' counters. The scene reloads
when one of its layer files changes. Serves on 127.0.0.1 unless --host says otherwise.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", help="the .usd* stage to inspect")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (loopback)")
    parser.add_argument("--port", type=int, default=8765, help="port (default 8765; 0: any)")
    parser.add_argument("--open", action="store_true", help="open the page in a browser")
    add_view_arguments(parser)
    add_predictor_argument(parser)
    parser.add_argument(
        "--reference",
        action="store_true",
        help="also render the skinned mesh: reference, side by side and error views",
    )
    add_source_argument(
        parser, "drive the live binding NAME from URL instead of its authored source"
    )
    add_regions_argument(parser)


def _check_port(host: str, port: int) -> None:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise RigspaceError(
                f"Cannot serve on {host}:{port} ({exc.strerror or exc}).",
                "choose another --port (or --port 0 for any free one).",
            ) from None


def build(
    scene: str,
    *,
    camera: str | None = None,
    resolution: tuple[int, int] = (640, 360),
    reference: bool = False,
    sources: dict[str, str] | None = None,
    renderer: str = "auto",
    predictor: str = "auto",
    regions: bool = True,
) -> Viewer:
    """The viewer of one scene, its engines open (or `frames.error` saying why not)."""
    from rigspace.runtime.view.scene import SceneModel
    from rigspace.runtime.view.server import Viewer
    from rigspace.runtime.view.viewport import FrameService

    model = SceneModel(scene)
    width, height = resolution
    frames = FrameService(scene, model.lock, width=width, height=height, reference=reference,
                          sources=sources, renderer=renderer,
                          predictor=predictor, regions=regions)  # fmt: skip
    frames.open(camera)
    return Viewer(model, frames)


def server(viewer: Viewer, host: str = "127.0.0.1", port: int = 8765) -> uvicorn.Server:
    import uvicorn

    from rigspace.runtime.view.server import create_app

    config = uvicorn.Config(create_app(viewer, host), host=host, port=port,
                            log_level="warning", ws="websockets-sansio")  # fmt: skip
    return uvicorn.Server(config)


def url_of(srv: uvicorn.Server, host: str) -> str:
    port = srv.servers[0].sockets[0].getsockname()[1]
    return f"http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port}/"


def in_background(viewer: Viewer, host: str = "127.0.0.1") -> tuple[uvicorn.Server, str]:
    """Serve `viewer` on a free port from a thread (tests, the bench); set `should_exit`
    on the returned server to stop it."""
    srv = server(viewer, host, 0)
    thread = threading.Thread(target=srv.run, daemon=True, name="rigspace-view-server")
    thread.start()
    while not srv.started:
        if not thread.is_alive():
            raise RigspaceError(f"The viewer could not serve on {host}.", "see the log above.")
        time.sleep(0.02)
    return srv, url_of(srv, host)


def run(args: argparse.Namespace) -> int:
    if not 0 <= args.port <= 65535:
        raise RigspaceError(f"--port {args.port} is not a port.", "give 0 to 65535.")
    _check_port(args.host, args.port)
    from rigspace.runtime.view.server import LOOPBACK  # starlette: only once it serves

    if args.host not in LOOPBACK:
        print(
            f"rigspace view: warning: --host {args.host} makes the viewer reachable from other "
            "machines; it has no login.",
            file=sys.stderr,
        )
    viewer = build(args.scene, camera=args.camera, resolution=args.resolution,
                   reference=args.reference, sources=dict(args.source),
                   renderer=args.renderer, predictor=args.predictor,
                   regions=not args.no_regions)  # fmt: skip
    if viewer.frames.error and args.source:
        # --source asks for a live pose: without frames there is nothing to drive.
        viewer.close()
        raise RigspaceError(viewer.frames.error)
    if viewer.frames.error:
        print(f"rigspace view: warning: no frames: {viewer.frames.error}", file=sys.stderr)
    if viewer.frames.live_error:
        print(f"rigspace view: warning: {viewer.frames.live_error}", file=sys.stderr)
    srv = server(viewer, args.host, args.port)

    def announce() -> None:
        while not srv.started:
            if srv.should_exit:
                return
            time.sleep(0.05)
        url = url_of(srv, args.host)
        print(f"rigspace view: serving {args.scene} on {url}", flush=True)
        if args.open:
            webbrowser.open(url)

    threading.Thread(target=announce, daemon=True).start()
    try:
        srv.run()
    finally:
        viewer.close()
    return 0


COMMAND = CommandSpec(
    name="view",
    help="inspect a scene in the browser: prims, properties, composition, frames, decisions",
    description=DESCRIPTION,
    add_arguments=add_arguments,
    run=run,
)

"""`python -m rigspace.apps.live_send URL --bvh FILE` (`rigspace live send`): stream a BVH clip
as a live source would, through rigspace.runtime.live.send."""

from __future__ import annotations

import argparse
import threading
from urllib.parse import urlsplit

from rigspace.apps.tools import run_tool
from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.send import humanoid_clip, send_vmc, serve_bvh
from rigspace.sdk.errors import RigspaceError


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """`python -m rigspace.apps.live_send URL --bvh FILE`: stream a BVH clip to a VMC
    receiver (vmc://HOST:PORT) or serve it to BVH-TCP clients (bvh+tcp://HOST:PORT)."""
    parser = _parser(prog)
    args = parser.parse_args(argv)
    return run_tool(parser.prog, lambda: _send(args))


def _send(args: argparse.Namespace) -> None:
    """Check the flags, read the clip, and send or serve it as the URL's scheme says."""
    if not args.speed > 0:
        raise RigspaceError(f"--speed {args.speed} is not a positive number.", "give --speed > 0.")
    skeleton, motion, frame_time = read_bvh(args.bvh)
    scheme = args.url.split("://", 1)[0].lower() if "://" in args.url else ""
    if scheme not in ("vmc", "bvh+tcp"):
        raise RigspaceError(
            f"{args.url!r} is not a URL this sender speaks.",
            "send to vmc://HOST:PORT or serve on bvh+tcp://HOST:PORT.",
        )
    stop = threading.Event()
    timer = threading.Timer(args.seconds or 0.0, stop.set)
    timer.daemon = True
    if scheme == "vmc":
        _send_vmc(args, skeleton, motion, frame_time, stop)
    else:
        if args.seconds is not None:  # how long the server serves
            timer.start()
        _serve_bvh(args, motion, frame_time, stop)
    timer.cancel()


def _parser(prog: str | None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog or "python -m rigspace.apps.live_send", description=main.__doc__
    )
    parser.add_argument("url", help="vmc://HOST:PORT or bvh+tcp://HOST:PORT")
    parser.add_argument(
        "--bvh", required=True, help="the clip (for example samples/motion/cmu_131_01.bvh)"
    )
    parser.add_argument("--speed", type=float, default=1.0, help="playback speed (1 = real time)")
    parser.add_argument("--loop", action="store_true", help="start the clip again at its end")
    parser.add_argument(
        "--seconds",
        type=float,
        default=None,
        help="stop after this long (VMC: after the frames of this long, at --speed, in real time)",
    )
    return parser


def _send_vmc(
    args: argparse.Namespace, skeleton, motion, frame_time: float, stop: threading.Event
) -> None:
    """vmc://: send the clip's humanoid poses to the receiver, and say how many frames went."""
    rotations, roots = skeleton.pose(motion)
    clip = humanoid_clip(skeleton, rotations, roots, frame_time)
    # --seconds: the frames of that long, whatever the preparation took or a busy
    # machine holds the sender back (it catches up): a count, not a clock.
    frames = None
    if args.seconds is not None:
        frames = round(args.seconds * args.speed / clip.frame_time)
    sent = send_vmc(args.url, clip, args.speed, args.loop, stop, frames)
    print(f"sent {sent} frames to {args.url}")


def _serve_bvh(args: argparse.Namespace, motion, frame_time: float, stop: threading.Event) -> None:
    """bvh+tcp://: serve the clip's motion lines to the clients until STOP, and say how many."""
    parts = urlsplit(args.url)
    try:
        sent = serve_bvh(
            parts.hostname or "127.0.0.1", parts.port or 7001, motion, frame_time,
            args.speed, stop, args.loop,
        )  # fmt: skip
    except OSError as exc:
        raise RigspaceError(
            f"Cannot serve on {args.url} ({exc.strerror or exc}).",
            "choose a free port in the URL.",
        ) from None
    print(f"served {sent} lines on {args.url}")


if __name__ == "__main__":
    raise SystemExit(main())

"""The command-line options that render, live and view share, defined once (their types and
help), so the three commands read `--camera`, `--resolution`, `--renderer` and `--source`
alike (and --no-regions)."""

from __future__ import annotations

import argparse
import math


def resolution(text: str) -> tuple[int, int]:
    """WxH -> (width, height)."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WxH, e.g. 640x360") from None
    return w, h


def positive(text: str) -> int:
    """A whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive whole number")
    return value


def positive_seconds(text: str) -> float:
    """A finite number of seconds > 0."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of seconds")
    return value


def source(text: str) -> tuple[str, str]:
    """NAME=URL -> (binding name, source URL)."""
    name, sep, url = text.partition("=")
    if not sep or not name or "://" not in url:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not NAME=URL, e.g. suit=vmc://127.0.0.1:39539"
        )
    return name, url


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    """--camera, --resolution and --renderer: what a command draws the stage with."""
    parser.add_argument("--camera", help="Camera prim path (default: the stage's first camera)")
    parser.add_argument(
        "--resolution",
        type=resolution,
        default=(640, 360),
        metavar="WxH",
        help="image width x height in pixels (default 640x360)",
    )
    parser.add_argument(
        "--renderer", default="auto", help="renderer for the scene prims: gl, embree, auto"
    )


def add_regions_argument(parser: argparse.ArgumentParser) -> None:
    """--no-regions: draw each character's body alone (docs/regions.md, "Runtime")."""
    parser.add_argument(
        "--no-regions",
        action="store_true",
        help="draw each character's body alone, not the regions its bundle lists (the face, "
        "a hand: networks of their own, drawn over the body where the camera is close; "
        "docs/regions.md)",
    )


def add_source_argument(parser: argparse.ArgumentParser, help: str) -> None:
    """--source NAME=URL, repeatable: a live binding's source given on the command line."""
    parser.add_argument(
        "--source", type=source, action="append", default=[], metavar="NAME=URL", help=help
    )

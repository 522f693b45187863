"""`rigspace capture`: render a neural character's training dataset from its capture ring."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from rigspace.sdk.cli import CommandSpec, time_range
from rigspace.sdk.errors import RigspaceError

if TYPE_CHECKING:
    from rigspace.capture.pipeline import CaptureResult
    from rigspace.capture.settings import CaptureOverrides

DESCRIPTION = """\
Render a neural character's training dataset: for every frame of its clips and every
camera of its capture ring (RigspaceCaptureRingAPI), the character's maps as one EXR
(R,G,B albedo, A mask, Z depth, N.X/N.Y/N.Z normals; uv.U, uv.V and chart, the textured
surface's st and chart, when the character has textures) and its rig parameters
(params.npz), with manifest.json, charts.json and contact_sheet.png. Flags override the
capture ring's values; the resolved settings are saved. Resumable (--resume, also after
kill -9 or SIGTERM) and shardable (--shard i/n: run n processes or machines on one folder,
any order).
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", help="the .usd* scene with the neural character")
    parser.add_argument(
        "--character",
        help="the RigspaceNeuralCharacter prim path (default: the scene's only one)",
    )
    parser.add_argument("--out", required=True, help="dataset folder (new, or to resume)")
    _add_ring_arguments(parser)
    _add_render_arguments(parser)
    _add_region_arguments(parser)
    _add_run_arguments(parser)


def _add_ring_arguments(parser: argparse.ArgumentParser) -> None:
    """The capture ring's cameras and what they capture: --views ... --frames | --clips."""
    parser.add_argument("--views", type=int, help="training views per ring")
    parser.add_argument("--elevations", type=float, nargs="+", help="ring elevations, degrees")
    parser.add_argument("--resolution", type=int, help="image size, a power of two")
    parser.add_argument(
        "--radius", type=float, help="camera distance from the look-at joint, scene units"
    )
    choose = parser.add_mutually_exclusive_group()
    choose.add_argument(
        "--frames", type=time_range, metavar="A:B", help="capture time codes A to B as one clip"
    )
    choose.add_argument("--clips", nargs="+", help="capture only these clips of the ring")
    parser.add_argument(
        "--held-out-clips",
        nargs="*",
        metavar="NAME",
        help="hold these of the ring's clips out of training instead of its heldOutClips; "
        "given without a name, none: every clip trains (a model for the shot that plays them "
        "all; its held-out views still measure it)",
    )


def _add_render_arguments(parser: argparse.ArgumentParser) -> None:
    """How the frames are rendered and cut into work items: --renderer ... --shard."""
    # The defaults of these are CaptureOverrides' and said in the help; None here tells a flag
    # given from one left out, which --resume takes from the capture's capture.json.
    parser.add_argument(
        "--renderer",
        help="gl, embree, or auto (default auto: gl when EGL works; embree for a character of "
        "over 250,000 triangles where GL is a software rasteriser)",
    )
    parser.add_argument(
        "--samples", type=int, help="anti-aliasing: s x s samples per pixel (default 2)"
    )
    parser.add_argument(
        "--every",
        type=int,
        metavar="N",
        help="capture every Nth frame of each clip (default 1: all; a small evaluation set, "
        "e.g. at a high --resolution)",
    )
    parser.add_argument(
        "--frames-per-item",
        type=int,
        help="frames per work item, the unit of sharding (default 16)",
    )
    parser.add_argument(
        "--shard", default="0/1", metavar="i/n", help="capture only work items i, i+n, ..."
    )


def _add_region_arguments(parser: argparse.ArgumentParser) -> None:
    """The character's regions: --region NAME | --regions."""
    regions = parser.add_mutually_exclusive_group()
    regions.add_argument(
        "--region",
        metavar="NAME",
        help="capture the dataset of the character's region NAME (RigspaceRegionAPI:NAME: its "
        "own ring around its joint, its resolution, its surface alone) into --out instead of "
        "the whole character's (docs/regions.md)",
    )
    regions.add_argument(
        "--regions",
        action="store_true",
        help="after the whole character, capture each of its regions into OUT/regions/NAME",
    )


def _add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Where and how the capture runs: --resume, --workers, --ray."""
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the capture in --out with the settings its capture.json saved (the "
        "character and every flag above left out)",
    )
    parser.add_argument("--workers", type=int, help="processes (default: one per core)")
    parser.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run the work items as Ray tasks: auto (the running cluster), a cluster address, "
        "or a local cluster when no ADDRESS is given; --out must be a folder every node sees "
        "(docs/scale.md)",
    )


def _character_and_flags(args: argparse.Namespace) -> tuple[str | None, dict[str, Any]]:
    """The character and the CaptureOverrides fields the command line gives; with --resume,
    what the capture was started with for every flag left out."""
    from rigspace.capture.dataset import saved_flags

    flags = {
        "views": args.views,
        "elevations": tuple(args.elevations) if args.elevations else None,
        "resolution": args.resolution,
        "radius": args.radius,
        "frames": args.frames,
        "clips": tuple(args.clips) if args.clips else None,
        "held_out_clips": None if args.held_out_clips is None else tuple(args.held_out_clips),
        "renderer": args.renderer,
        "samples_per_axis": args.samples,
        "frames_per_item": args.frames_per_item,
        "every": args.every,
    }
    given = {name: value for name, value in flags.items() if value is not None}
    character = args.character
    saved = saved_flags(args.out) if args.resume else None
    if saved is not None:  # what the capture was started with, for every flag left out
        if "frames" in given or "clips" in given:  # the other one of the two is not kept
            saved = {k: v for k, v in saved.items() if k not in ("frames", "clips")}
        character = character or saved["character"]
        given = {**{k: v for k, v in saved.items() if k in flags}, **given}
    return character, given


def _only_character(scene: str) -> str:
    """The prim path of the scene's one neural character (an error naming them otherwise)."""
    from rigspace.capture.settings import CaptureError
    from rigspace.sdk import schema
    from rigspace.sdk.stage import open_stage
    from rigspace.sdk.validation import require_readable

    stage = open_stage(scene)
    require_readable(stage, "capture", exception=CaptureError)  # a character may be in it
    found = [str(p.GetPath()) for p in schema.neural_characters(stage)]
    if len(found) != 1:
        raise RigspaceError(
            f"{scene} has {len(found)} neural characters ({', '.join(found) or 'none'}).",
            "pass --character with the prim path.",
        )
    return found[0]


def _capture_character(
    args: argparse.Namespace, character: str, overrides: CaptureOverrides
) -> CaptureResult:
    """The whole character's dataset (or --region's) into --out, on Ray with --ray."""
    from rigspace.capture.pipeline import capture, parse_shard

    if args.ray is not None:
        from rigspace.capture.ray_capture import capture_on_ray

        return capture_on_ray(
            args.scene,
            character,
            args.out,
            overrides,
            address=args.ray,
            shard=parse_shard(args.shard),
            resume=args.resume,
            workers=args.workers,
        )
    return capture(
        args.scene,
        character,
        args.out,
        overrides,
        shard=parse_shard(args.shard),
        resume=args.resume,
        workers=args.workers,
        region=args.region,
    )


def _capture_regions(args: argparse.Namespace, character: str, overrides: CaptureOverrides) -> None:
    """--regions: each of the character's regions into OUT/regions/NAME, printing each summary."""
    from pathlib import Path

    from rigspace.capture.pipeline import capture, parse_shard
    from rigspace.sdk import schema
    from rigspace.sdk.stage import open_stage

    stage = open_stage(args.scene)  # kept in a variable: its prims expire with it
    for region in schema.region_names(stage.GetPrimAtPath(character)):
        out = Path(args.out) / "regions" / region
        resume = args.resume and (out / "capture.json").is_file()
        print(f"region {region} -> {out}", file=sys.stdout)
        part = capture(
            args.scene, character, out, overrides, shard=parse_shard(args.shard),
            resume=resume, workers=args.workers, region=region,
        )  # fmt: skip
        print(part.summary(), file=sys.stdout)


def run(args: argparse.Namespace) -> int:
    # Imported here so `rigspace --help` stays fast and loads no renderer.
    from rigspace.capture.settings import CaptureError, CaptureOverrides

    character, given = _character_and_flags(args)
    if character is None:
        character = _only_character(args.scene)
    overrides = CaptureOverrides(**given)  # a flag left out: its default
    if args.ray is not None and (args.region or args.regions):
        raise CaptureError(
            "--ray captures the whole character only.",
            "capture its regions on this machine (--region NAME), or leave out --ray.",
        )
    print(_capture_character(args, character, overrides).summary(), file=sys.stdout)
    if args.regions:
        _capture_regions(args, character, overrides)
    return 0


COMMAND = CommandSpec(
    name="capture",
    help="render a neural character's training dataset from its capture ring",
    description=DESCRIPTION,
    add_arguments=add_arguments,
    run=run,
)

"""`rigspace render`: a stage's frames with its neural characters, as EXR, PNG, mp4 and a report."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from rigspace.sdk.cli import CommandSpec, time_range
from rigspace.sdk.errors import RigspaceError

DESCRIPTION = """\
Render a USD stage's frames with its neural characters drawn by their model bundles:
per frame one EXR (R,G,B,A lit beauty premultiplied; albedo.R/G/B; N.X/N.Y/N.Z camera
normals; Z depth), a PNG of the beauty, and report.json (per frame: what each character
cost and what was skipped or reused, and why). --video adds an mp4; a contact sheet of
a few frames is written as contact_sheet.png.
"""
CONTACT_FRAMES = 6


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WxH, e.g. 640x360") from None
    return w, h


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive whole number")
    return value


def _aovs(text: str) -> tuple[str, ...]:
    from rigspace.runtime.engine import AOVS

    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in AOVS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"{text!r}: choose a comma-separated list from {', '.join(AOVS)}"
        )
    return names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", help="the .usd* stage to render")
    parser.add_argument(
        "--out", required=True, help="folder for frames, report.json, contact sheet"
    )
    parser.add_argument("--camera", help="Camera prim path (default: the stage's first camera)")
    parser.add_argument(
        "--frames", type=time_range, metavar="A:B", help="time codes (default: the stage's range)"
    )
    parser.add_argument("--step", type=float, default=1.0, help="time codes between frames")
    parser.add_argument("--resolution", type=_resolution, default=(640, 360), metavar="WxH")
    parser.add_argument("--video", help="also write this mp4 (OpenCV mp4v)")
    parser.add_argument(
        "--renderer", default="auto", help="renderer for the scene prims: gl, embree, auto"
    )
    parser.add_argument("--int8", action="store_true", help="evaluate the int8 graphs")
    parser.add_argument(
        "--prim-samples",
        type=_positive,
        default=2,
        metavar="N",
        help="N x N samples per pixel for the scene prims (default 2; 1: no anti-aliasing, faster)",
    )
    parser.add_argument(
        "--max-level",
        type=_positive,
        metavar="R",
        help="cap the characters' level of detail at R x R (faster, less detail)",
    )
    parser.add_argument(
        "--aovs",
        type=_aovs,
        default=None,
        metavar="LIST",
        help="images written to the EXRs, comma-separated from beauty, albedo, normal, depth, "
        "mask (default: all). Without normal and depth, unlit characters that nothing "
        "overlaps run their albedo branch only",
    )
    parser.add_argument(
        "--reference",
        action="store_true",
        help="also render the real skinned mesh instead of the network; write neural | "
        "reference | error images and each character region's PSNR",
    )


def run(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np
    from tqdm import tqdm

    from rigspace.runtime.engine import AOVS, Engine
    from rigspace.runtime.output import write_frame_exr
    from rigspace.sdk.color import linear_to_srgb

    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RigspaceError(
            f"--out {out} cannot be created ({exc}).", "choose a writable folder."
        ) from exc
    width, height = args.resolution
    aovs = args.aovs or AOVS
    engine = Engine(
        args.scene, camera=args.camera, width=width, height=height,
        renderer=args.renderer, precision="int8" if args.int8 else "fp32", aovs=aovs,
        prim_samples=args.prim_samples, max_level=args.max_level,
    )  # fmt: skip
    truth = None
    if args.reference:
        truth = Engine(args.scene, camera=args.camera, width=width, height=height,
                       renderer=args.renderer, reference=True, aovs=aovs,
                       prim_samples=args.prim_samples)  # fmt: skip
    first, last = args.frames or (engine.stage.GetStartTimeCode(), engine.stage.GetEndTimeCode())
    if args.step <= 0 or last < first:
        raise RigspaceError(
            f"--frames {first:g}:{last:g} with --step {args.step:g} is empty.",
            "use A:B with A <= B and a positive step.",
        )
    times = np.arange(first, last + 1e-9, args.step)
    video = None
    if args.video:
        video = cv2.VideoWriter(
            args.video,
            cv2.VideoWriter.fourcc(*"mp4v"),
            engine.stage.GetFramesPerSecond() / args.step,
            (width, height),
        )
        if not video.isOpened():
            raise RigspaceError(
                f"--video {args.video} cannot be written.", "choose a writable .mp4 path."
            )
    reports, thumbs = [], []
    picks = set(
        np.linspace(0, len(times) - 1, min(CONTACT_FRAMES, len(times))).astype(int).tolist()
    )
    try:
        for k, t in enumerate(tqdm(times, unit="frame", file=sys.stderr, dynamic_ncols=True)):
            frame = engine.render(float(t))
            stem = f"frame_{t:08.1f}"
            write_frame_exr(out / f"{stem}.exr", frame, aovs)
            png = (linear_to_srgb(frame.beauty) * 255 + 0.5).astype(np.uint8)[..., ::-1]
            cv2.imwrite(str(out / f"{stem}.png"), png)
            if video is not None:
                video.write(png)
            if k in picks:
                thumbs.append(png)
            if truth is not None:
                frame.report["reference"] = compare_with_reference(
                    frame, truth.render(float(t)), out / f"compare_{t:08.1f}.png"
                )
            reports.append(frame.report)
    finally:
        engine.close()
        if truth is not None:
            truth.close()
        if video is not None:
            video.release()
    cv2.imwrite(str(out / "contact_sheet.png"), contact_sheet(thumbs))
    tmp = out / f".report.json.{os.getpid()}.tmp"
    tmp.write_text(
        json.dumps(
            {"scene": str(args.scene), "resolution": [width, height], "frames": reports}, indent=2
        )
        + "\n"
    )
    os.replace(tmp, out / "report.json")
    totals = np.array([r["seconds"]["total"] for r in reports])
    counts = {k: sum(r["counts"][k] for r in reports) for k in reports[0]["counts"]}
    if truth is not None:
        rows = [c for r in reports for c in r["reference"] if c["psnr"] is not None]
        if rows:
            beauty, albedo = [c["psnr"] for c in rows], [c["albedo_psnr"] for c in rows]
            print(
                f"reference: character region, median over {len(rows)} character frames: beauty "
                f"PSNR {np.median(beauty):.2f} dB (min {min(beauty):.2f}), albedo PSNR "
                f"{np.median(albedo):.2f} dB (the region holds the prims behind it too)"
            )
    print(
        f"rendered {len(reports)} frames at {width}x{height} into {out} "
        f"(median {1e3 * float(np.median(totals)):.1f} ms/frame)"
        + (f"; video {args.video}" if args.video else "")
    )
    print(
        "characters: "
        + ", ".join(f"{k} {v}" for k, v in counts.items() if v or k in ("evaluated", "reused"))
    )
    return 0


def compare_with_reference(frame, truth, path: Path) -> list[dict]:
    """PSNR of each evaluated character's region (lit beauty) against the reference frame,
    and an image neural | reference | 4x error."""
    import cv2
    import numpy as np

    from rigspace.sdk.color import linear_to_srgb

    results = []
    for entry in frame.report["characters"]:
        if "region" not in entry:
            results.append({"path": entry["path"], "psnr": None, "reason": entry.get("reason", "")})
            continue
        x, y, w, h = entry["region"]
        region = np.s_[y : y + h, x : x + w]
        results.append(
            {
                "path": entry["path"],
                "region": entry["region"],
                "psnr": _psnr(frame.beauty[region], truth.beauty[region]),
                "albedo_psnr": _psnr(frame.maps.albedo[region], truth.maps.albedo[region]),
            }
        )
    error = np.clip(4 * np.abs(frame.beauty - truth.beauty), 0, 1)
    row = np.concatenate(
        [linear_to_srgb(frame.beauty), linear_to_srgb(truth.beauty), error], axis=1
    )
    cv2.imwrite(str(path), (row * 255 + 0.5).astype(np.uint8)[..., ::-1])
    return results


def _psnr(a, b) -> float:
    """PSNR in dB of two images clipped to [0, 1] (peak 1)."""
    import numpy as np

    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return float(10 * np.log10(1 / max(mse, 1e-12)))


def contact_sheet(images: list, columns: int = 3):
    """Frames in a grid, row by row; a short last row is padded with black."""
    import numpy as np

    blank = np.zeros_like(images[0])
    rows = []
    for i in range(0, len(images), columns):
        row = images[i : i + columns]
        if len(images) > columns:
            row = row + [blank] * (columns - len(row))
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)


COMMAND = CommandSpec(
    name="render",
    help="render a stage's frames with its neural characters (EXR, PNG, mp4, report)",
    description=DESCRIPTION,
    add_arguments=add_arguments,
    run=run,
)

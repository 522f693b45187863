"""`rigspace render`: a stage's frames with its neural characters, as EXR, PNG, mp4 and a report."""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time as clock
from pathlib import Path
from typing import TYPE_CHECKING

from rigspace.runtime.options import add_regions_argument, add_view_arguments, positive
from rigspace.runtime.reference import NOTHING_TO_COMPARE, compare_with_reference, coverages
from rigspace.sdk.cli import CommandSpec, time_range
from rigspace.sdk.errors import RigspaceError, SceneError
from rigspace.sdk.files import write_atomic
from rigspace.sdk.predictors import add_predictor_argument

if TYPE_CHECKING:
    import numpy as np

DESCRIPTION = """\
Render a USD stage's frames with its neural characters drawn by their model bundles:
per frame one EXR (R,G,B,A lit beauty premultiplied; albedo.R/G/B; N.X/N.Y/N.Z camera
normals; Z depth), a PNG of the beauty, and report.json (per frame: what each character
cost and what was skipped or reused, and why). --video adds an H.264 mp4 that browsers
play; a contact sheet of a few frames is written as contact_sheet.png. The --out folder
is created only once the scene and flags are valid.
"""
CONTACT_FRAMES = 9
"""Evenly spaced frames on contact_sheet.png, three to a row (a 16:9 sheet of 16:9 frames)."""


def _aovs(text: str) -> tuple[str, ...]:
    from rigspace.runtime.engine import AOVS

    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in AOVS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"{text!r}: choose a comma-separated list from {', '.join(AOVS)}"
        )
    return names


def _model(text: str) -> tuple[str, str]:
    """argparse type for --model [PRIM=]BUNDLE: (prim path or "", bundle folder)."""
    prim, sep, bundle = text.partition("=")
    if sep and prim.startswith("/"):
        return prim, bundle
    return "", text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", help="the .usd* stage to render")
    parser.add_argument(
        "--out", required=True, help="folder for frames, report.json, contact sheet"
    )
    add_view_arguments(parser)
    parser.add_argument(
        "--frames", type=time_range, metavar="A:B", help="time codes (default: the stage's range)"
    )
    parser.add_argument("--step", type=float, default=1.0, help="time codes between frames")
    parser.add_argument("--video", help="also write this mp4 (H.264, yuv420p)")
    parser.add_argument("--int8", action="store_true", help="evaluate the int8 graphs")
    add_predictor_argument(parser)
    parser.add_argument(
        "--model",
        action="append",
        type=_model,
        default=[],
        metavar="[PRIM=]BUNDLE",
        help="draw this model bundle for the neural character PRIM (PRIM= may be left out when "
        "the stage has one) instead of its rigspace:model; the scene file is not edited "
        "(a model just trained, before the scene names it)",
    )
    parser.add_argument(
        "--prim-samples",
        type=positive,
        default=2,
        metavar="N",
        help="N x N samples per pixel for the scene prims (default 2; 1: no anti-aliasing, faster)",
    )
    parser.add_argument(
        "--max-level",
        type=positive,
        metavar="R",
        help="cap the characters' level of detail at R x R (faster, less detail)",
    )
    parser.add_argument(
        "--no-textures",
        action="store_true",
        help="colour characters from their albedo branch even where their bundle has a texture "
        "head (the network's image alone, for comparison)",
    )
    add_regions_argument(parser)
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

    from rigspace.runtime.engine import AOVS, Engine, EngineSettings
    from rigspace.runtime.output import VideoWriter

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise RigspaceError(
            f"--out {out} is a file, not a folder.", "choose a folder for the frames."
        )
    width, height = args.resolution
    aovs = args.aovs or AOVS
    settings = EngineSettings(
        camera=args.camera, width=width, height=height, renderer=args.renderer,
        precision="int8" if args.int8 else "fp32", aovs=aovs, prim_samples=args.prim_samples,
        max_level=args.max_level, textures=not args.no_textures, predictor=args.predictor,
        models=dict(args.model), regions=not args.no_regions,
    )  # fmt: skip
    engine = Engine(args.scene, settings)
    truth = None
    video = None
    try:
        if args.reference:
            truth = Engine(args.scene, EngineSettings(
                camera=args.camera, width=width, height=height, renderer=args.renderer,
                reference=True, aovs=aovs, prim_samples=args.prim_samples, models=dict(args.model),
            ))  # fmt: skip
        times = frame_times(args.frames, args.step, engine.stage)
        if truth is not None:
            check_reference_poses(truth, times)
        # The input is valid: only now does the output folder appear.
        created = make_folder(out)
        if args.video:
            try:
                video = VideoWriter(
                    args.video, width, height, engine.stage.GetFramesPerSecond() / args.step
                )
            except (OSError, ValueError) as exc:  # av's errors derive from both
                remove_empty(created)
                raise RigspaceError(
                    f"--video {args.video} cannot be written ({exc}).",
                    "choose a writable .mp4 path in an existing folder.",
                ) from exc
        reports, thumbs = _render_frames(engine, truth, video, times, out, aovs)
    finally:
        engine.close()
        if truth is not None:
            truth.close()
        if video is not None:
            video.close()
    cv2.imwrite(str(out / "contact_sheet.png"), contact_sheet(thumbs))
    paths = [c.path for c in engine.characters]
    warnings = (
        never_drawn(reports, paths)
        + draws_nothing(reports, paths)
        + novel_views(reports, engine.characters)
    )
    for warning in warnings:
        print(f"rigspace render: warning: {warning}", file=sys.stderr)
    warnings = engine.region_warnings + warnings  # said when the engine loaded them
    _write_report(out, args, engine, warnings, reports)
    _print_totals(args, out, reports, truth is not None)
    return 0


def _render_frames(engine, truth, video, times, out: Path, aovs) -> tuple[list[dict], list]:
    """Render, write and compare every frame: the frames' reports and the contact sheet's."""
    import cv2
    import numpy as np
    from tqdm import tqdm

    from rigspace.runtime.output import write_frame_exr
    from rigspace.sdk.color import linear_to_srgb

    reports, thumbs = [], []
    picks = set(
        np.linspace(0, len(times) - 1, min(CONTACT_FRAMES, len(times))).astype(int).tolist()
    )
    for k, t in enumerate(tqdm(times, unit="frame", file=sys.stderr, dynamic_ncols=True)):
        began = clock.perf_counter()
        frame = engine.render(float(t))
        if k == 0 and clock.perf_counter() - began > FIRST_FRAME_NOTE:
            tqdm.write(
                f"rigspace render: the first frame took {clock.perf_counter() - began:.0f} s: "
                "numba compiled the shadow and texture kernels (cached on disk now; "
                ".ci/setup compiles them ahead), and the network sessions loaded",
                file=sys.stderr,
            )
        stem = f"frame_{t:08.1f}"
        write_frame_exr(out / f"{stem}.exr", frame, aovs)
        rgb = (linear_to_srgb(frame.beauty) * 255 + 0.5).astype(np.uint8)
        png = rgb[..., ::-1]
        cv2.imwrite(str(out / f"{stem}.png"), png)
        if video is not None:
            video.write(rgb)
        if k in picks:
            thumbs.append(png)
        report = frame.report.to_json()  # with what render adds: reference, covered_px
        if truth is not None:
            report["reference"] = compare_with_reference(
                frame,
                truth.render(float(t)),
                out / f"compare_{t:08.1f}.png",
                coverages(engine, truth, float(t)),
            )
        for entry in report["characters"]:  # what each drawn character covers
            if entry.get("decision") in ("evaluated", "reused"):
                coverage = engine.coverage_of(entry["path"], float(t))
                entry["covered_px"] = 0 if coverage is None else int((coverage >= 0.5).sum())
        reports.append(report)
    return reports, thumbs


def _write_report(
    out: Path, args: argparse.Namespace, engine, warnings: list[str], reports: list[dict]
) -> None:
    """report.json in `out`, replaced at once (sdk.files.write_atomic)."""
    width, height = args.resolution
    write_atomic(
        out / "report.json",
        json.dumps(
            {
                "scene": str(args.scene),
                "resolution": [width, height],
                "predictors": sorted({c.model.runner.description for c in engine.characters}),
                "warnings": warnings,
                "frames": reports,
            },
            indent=2,
        )
        + "\n",
    )


def _print_totals(
    args: argparse.Namespace, out: Path, reports: list[dict], reference: bool
) -> None:
    """The console's closing lines: the reference summary, frames, timing and decisions."""
    import numpy as np

    width, height = args.resolution
    totals = np.array([r["seconds"]["total"] for r in reports])
    counts = {k: sum(r["counts"][k] for r in reports) for k in reports[0]["counts"]}
    if reference:
        print(reference_summary(reports))
    print(
        f"rendered {len(reports)} frames at {width}x{height} into {out} "
        f"(median {1e3 * float(np.median(totals)):.1f} ms/frame)"
        + (f"; video {args.video} (H.264)" if args.video else "")
    )
    print(
        "characters: "
        + ", ".join(f"{k} {v}" for k, v in counts.items() if v or k in ("evaluated", "reused"))
    )


def never_drawn(reports: list[dict], characters: list[str]) -> list[str]:
    """A sentence per neural character (with a model) that no frame drew, with the reason
    most frames gave: an empty shot is said, not left for the viewer to find."""
    from collections import Counter

    warnings = []
    for path in characters:
        entries = [e for r in reports for e in r["characters"] if e.get("path") == path]
        if not entries or any(e.get("decision") in ("evaluated", "reused") for e in entries):
            continue
        reason, count = Counter(str(e.get("reason", "")) for e in entries).most_common(1)[0]
        warnings.append(
            f"{path} is in none of the {len(reports)} frames: {reason} ({count} of them)."
        )
    return warnings


def novel_views(reports: list[dict], characters: list) -> list[str]:
    """A sentence per body or region (NeuralPart) whose evaluated frames saw its look-at
    joint further than NOVEL_VIEW_DEG outside the views its network learned (the frames'
    `novel_view`): which frames, how far, which way, and the ring that would cover them
    (sdk.view_coverage)."""
    from collections import Counter

    from rigspace.sdk.view_coverage import NOVEL_VIEW_DEG, advice

    warnings = []
    for character in characters:
        for part in [character, *character.regions]:
            seen: list[tuple[float, float, str]] = []
            for r in reports:
                for e in r["characters"]:
                    if e.get("path") != character.path:
                        continue
                    if part is not character:
                        e = next((x for x in e.get("regions", ()) if x["name"] == part.name), {})
                    if "novel_view_deg" in e:
                        seen.append((r["time"], e["novel_view_deg"], e.get("novel_view", "")))
            far = [(t, d, way) for t, d, way in seen if way]
            if not far or part.views is None:
                continue
            way = Counter(way for _, _, way in far).most_common(1)[0][0]
            worst = max(d for _, d, _ in far)
            held = (part.views.held_out or {}).get("median")
            attribute = (
                "rigspace:captureRing:elevations"
                if part is character
                else f"rigspace:region:{part.name}:elevations"
            )
            joint = character.rig.joints[part.look_at].rsplit("/", 1)[-1]
            warnings.append(
                f"{character.path}'s {part.name} network: in {len(far)} of {len(seen)} frames "
                f"({_spans([t for t, _, _ in far])}) the camera saw its joint {joint} up to "
                f"{worst:.1f} deg outside the views it learned (more than {NOVEL_VIEW_DEG:g}), "
                f"mostly {way}"
                + (
                    f" (its held-out views: {held:.1f} deg outside, median)"
                    if held is not None
                    else ""
                )
                + ": there its image is a guess, an average of the views it learned. To cover "
                "them, " + advice(way, worst, part.views.elevations, attribute) + "."
            )
    return warnings


def _spans(times: list[float]) -> str:
    """Time codes as spans: [440, 460, 480, 600] -> "440-480, 600" (consecutive in the
    list's own step)."""
    step = min((b - a for a, b in itertools.pairwise(times)), default=0.0)
    spans: list[list[float]] = []
    for t in times:
        if spans and t - spans[-1][1] <= step + 1e-6:
            spans[-1][1] = t
        else:
            spans.append([t, t])
    return ", ".join(f"{a:g}" if a == b else f"{a:g}-{b:g}" for a, b in spans)


def draws_nothing(reports: list[dict], characters: list[str]) -> list[str]:
    """A sentence per neural character whose network covered no pixel (coverage >= 0.5) in
    any frame it drew at MIN_DRAWN_PX or more: the shot shows the set where the character
    should be, a model that is untrained or not this character's."""
    warnings = []
    for path in characters:
        drawn = [
            e
            for r in reports
            for e in r["characters"]
            if e.get("path") == path and "covered_px" in e and e.get("size_px", 0) >= MIN_DRAWN_PX
        ]
        if drawn and not any(e["covered_px"] for e in drawn):
            n = len(drawn)
            warnings.append(
                f"{path}: the model draws nothing: its mask is empty on {n} of {n} frames it "
                "was drawn in (no pixel's coverage reaches 0.5; untrained, or the wrong bundle "
                "for this character?)."
            )
    return warnings


MIN_DRAWN_PX = 8.0
"""A billboard this many pixels across or more, drawn by a trained network, covers pixels:
an empty mask there is the model's, not the size's."""
FIRST_FRAME_NOTE = 10.0
"""Seconds a first frame may take before render says why it was slow (a first run)."""
MAX_FRAMES = 1_000_000
"""The most frames one render may ask for: over nine hours at 30 fps. More is a typo in
--frames or --step (a 1e12 or a 1e-9), which would otherwise exhaust memory before the
first frame."""


def frame_times(frames: tuple[float, float] | None, step: float, stage) -> np.ndarray:
    """The time codes to render: --frames A:B every --step (default: the stage's range).

    Refuses a range that is not finite, empty, too long, or wholly outside the stage's
    authored time range; warns (on stderr) when it reaches past either end, where USD holds
    the first or last time sample.
    """
    import numpy as np

    start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
    first, last = frames or (start, end)
    flag = f"--frames {first:g}:{last:g}"
    if not (math.isfinite(first) and math.isfinite(last)):
        raise RigspaceError(
            f"{flag} is not a range of time codes.", "give two finite numbers, e.g. --frames 0:120."
        )
    if not (math.isfinite(step) and step > 0):
        raise RigspaceError(
            f"--step {step:g} is not a positive number of time codes.",
            "use e.g. --step 1 (every frame) or --step 10.",
        )
    if last < first:
        raise RigspaceError(
            f"{flag} with --step {step:g} is empty.", "use A:B with A <= B and a positive step."
        )
    count = (last - first) / step + 1
    if count > MAX_FRAMES:
        raise RigspaceError(
            f"{flag} with --step {step:g} is {count:.3g} frames.",
            f"render at most {MAX_FRAMES:,} at once: a shorter range or a larger --step.",
        )
    if stage.HasAuthoredTimeCodeRange():
        # Compared as capture compares them (sdk.timecodes): a drifted export's range
        # 1.0000000521-3023.0001577 holds --frames 1:3023.
        before = _beyond(start, first)
        after = _beyond(last, end)
        where = f"the stage's time range {start:g}-{end:g}"
        if _beyond(start, last) or _beyond(first, end):
            raise RigspaceError(
                f"{flag} lies outside {where}.", f"choose frames within {start:g}:{end:g}."
            )
        if before or after:
            outside = [f"{first:g}-{start:g}"] if before else []
            outside += [f"{end:g}-{last:g}"] if after else []
            print(
                f"rigspace render: warning: {flag} reaches past {where}: frames "
                f"{' and '.join(outside)} show the stage held at its "
                f"{'first or last' if len(outside) == 2 else 'first' if before else 'last'}"
                " time sample.",
                file=sys.stderr,
            )
    # Counted, then spaced: arange(first, last + eps, step) loses the frame when last + eps
    # rounds to last (1e12) and a frame to rounding when (last - first) / step is whole.
    return first + step * np.arange(int(count + 1e-9))


def _beyond(a: float, b: float) -> bool:
    """Whether time code `a` lies after `b` by more than the time codes' tolerance."""
    from rigspace.sdk.timecodes import same_time

    return a > b and not bool(same_time(a, b))


def check_reference_poses(truth, times) -> None:
    """--reference draws each character's skinned mesh: refuse, before any frame, an
    animation that gives NaN or Inf joints, or skinned points beyond float32's range (finite
    joint translations near 3e38 add up past it), at a time to render. The network's render
    skips such a frame with a warning; the mesh cannot be drawn at all."""
    import numpy as np

    for character in truth.characters:
        for t in times:
            try:
                character.pose(float(t))
                with np.errstate(invalid="ignore", over="ignore"):  # the normals of inf points
                    meshes = character.rig.posed_meshes(float(t))
                bad = next((m.name for m in meshes if not np.all(np.isfinite(m.points))), None)
                what = f"points for {bad}"
            except SceneError:
                bad = what = "joint transforms"
            if bad is not None:
                animation = character.rig.animation.GetPath()
                raise SceneError(
                    f"--reference: the animation {animation} of {character.path} gives NaN or "
                    f"Inf {what} at time {t:g}, so the skinned mesh cannot be drawn.",
                    "fix the SkelAnimation's values there, or leave out --reference (the "
                    "network's render skips a frame without finite joints, with a warning).",
                )


def make_folder(out: Path) -> Path | None:
    """Create `out` (and missing parents); the topmost folder this created, else None."""
    missing = [p for p in (out, *out.parents) if not p.exists()]
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RigspaceError(
            f"--out {out} cannot be created ({exc}).", "choose a writable folder."
        ) from exc
    return missing[-1] if missing else None


def remove_empty(created: Path | None) -> None:
    """Remove the folders make_folder created, as long as they are still empty: a folder
    that existed before, or holds anything, is never removed."""
    if created is None:
        return
    for folder in sorted((p for p in created.rglob("*") if p.is_dir()), reverse=True):
        try:
            folder.rmdir()
        except OSError:
            return
    try:
        created.rmdir()
    except OSError:
        pass


def reference_summary(reports: list[dict]) -> str:
    """The console's line about the --reference comparison."""
    import numpy as np

    entries = [c for r in reports for c in r["reference"]]
    rows = [c for c in entries if c["psnr"] is not None]
    empty = sum(1 for c in entries if c.get("reason", "").startswith(NOTHING_TO_COMPARE))
    if not rows:
        return (
            f"reference: nothing to compare: no character covered a pixel in any of the "
            f"{len(entries)} character frames (report.json: psnr null, with the reason)."
            if empty
            else "reference: nothing to compare: no character was drawn by the network."
        )
    beauty, albedo = [c["psnr"] for c in rows], [c["albedo_psnr"] for c in rows]
    ious = [c["mask_iou"] for c in rows if c.get("mask_iou") is not None]
    flips = [(c["flip"], c["flip_ceiling"]) for c in rows if c.get("flip") is not None]
    return (
        f"reference: character region, median over {len(rows)} character frames: beauty "
        f"PSNR {np.median(beauty):.2f} dB (min {min(beauty):.2f}), albedo PSNR "
        f"{np.median(albedo):.2f} dB (the region holds the prims behind it too)"
        + (f", mask IoU {np.median(ious):.3f} (its own coverage)" if ious else "")
        + (
            f", beauty FLIP {np.median([f for f, _ in flips]):.4f} (0 is identical; the "
            f"reference squeezed to the network's size scores {np.median([c for _, c in flips]):.4f})"
            if flips
            else ""
        )
        + (f"; {empty} frames had nothing to compare (under a pixel)" if empty else "")
        + _regions_summary(rows)
    )


def _regions_summary(rows: list[dict]) -> str:
    """The reference line's part about the characters' regions (their own squares), if any."""
    import numpy as np

    by_name: dict[str, list[dict]] = {}
    for row in rows:
        for region in row.get("regions", ()):
            by_name.setdefault(region["name"], []).append(region)
    return "".join(
        f"; region {name}, its own square over {len(found)} frames: beauty PSNR "
        f"{np.median([r['psnr'] for r in found]):.2f} dB, FLIP "
        f"{np.median([r['flip'] for r in found]):.4f}"
        for name, found in sorted(by_name.items())
    )


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

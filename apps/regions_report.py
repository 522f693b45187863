"""How a character's parts look on screen against its skinned mesh, model against model.

    python -m rigspace.apps.regions_report SCENE --out DIR [--draw LABEL=BUNDLE[:body] ...]
        [--part NAME=JOINT ...] [--frames A:B] [--step N] [--width W] [--height H]

For each frame of the shot, the scene's neural character is drawn by each `--draw` (a model
bundle, with its regions, or `:body` for its body alone; default: the scene's own model with
its regions and without) and by its skinned mesh (the `--reference` frame). A **part** is a
surface of the mesh: each region the character declares (RigspaceRegionAPI: its joints'
skinned surface, as capture cuts it, capture/regions.py) and each `--part NAME=JOINT` (the
joint and those below it: `leftArm=upperarm_l`). A part's **own pixels** in a frame are those
where its surface is the nearest thing in the reference frame (hidden where a prim or another
part of the body is in front). Over them, per draw:

- beauty and albedo PSNR (pooled: one mean squared error over every frame's pixels) and the
  median of the frames' beauty PSNR;
- FLIP over the same pixels (rigspace.sdk.flip);
- mask IoU near the part: the draw's coverage against the mesh's over the part's pixels
  grown by NEAR_PX (a limb the network leaves out scores near 0 there; the body around it
  does not count).

Writes DIR/regions_report.json (the totals and, per part and draw, a row per frame: time,
pixels, beauty PSNR, FLIP, mask IoU), DIR/regions_report.md (a table per part, and the frames
where the draws differ most) and, per part, DIR/part_NAME.png: the frames where the part is
largest, reference then each draw, cropped around the part and enlarged (nearest neighbour) to
CROP_PX, so that a viewer sees what each draw makes of a face or the fingers at the size they
have on screen; with two draws or more, DIR/frames_NAME.png plots each draw's beauty PSNR frame
by frame (where along the shot one draw wins or loses). Nothing is written when a frame fails.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rigspace.capture.regions import RegionMeshes

NEAR_PX = 3
"""A part's pixels grown by this many pixels: where its mask IoU is measured."""
MIN_PIXELS = 16
"""A frame whose part covers fewer pixels than this does not count for that part."""
CROPS = 4
"""Frames shown per part image (those where the part covers the most pixels)."""
CROP_PX = 192
"""The side each crop is enlarged to in the part images."""
SPREAD_ROWS = 8
"""Frames listed per part in the markdown's "where the draws differ most"."""


@dataclass
class Tally:
    """One part's numbers under one draw, summed over frames."""

    pixels: int = 0
    beauty_se: float = 0.0
    albedo_se: float = 0.0
    flip_sum: float = 0.0
    iou_hits: int = 0
    iou_union: int = 0
    rows: list[dict] = field(default_factory=list)
    """Per frame measured: time, pixels, beauty PSNR, FLIP, mask IoU near the part."""

    def add(self, t: float, frame, truth, own: np.ndarray, near: np.ndarray, coverage) -> None:
        from rigspace.sdk.flip import flip_map

        count = int(own.sum())
        beauty = (np.clip(frame.beauty[own], 0, 1) - np.clip(truth.beauty[own], 0, 1)) ** 2
        albedo = (
            np.clip(frame.maps.albedo[own], 0, 1) - np.clip(truth.maps.albedo[own], 0, 1)
        ) ** 2
        self.pixels += count
        self.beauty_se += float(beauty.sum()) / 3
        self.albedo_se += float(albedo.sum()) / 3
        ys, xs = np.nonzero(near)
        box = np.s_[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
        flip = float(flip_map(frame.beauty[box], truth.beauty[box])[own[box]].sum())
        self.flip_sum += flip
        drawn, mesh = coverage
        a, b = (drawn >= 0.5) & near, (mesh >= 0.5) & near
        hits, union = int((a & b).sum()), int((a | b).sum())
        self.iou_hits += hits
        self.iou_union += union
        self.rows.append(
            {
                "t": t,
                "pixels": count,
                "psnr": _psnr(float(beauty.mean())),
                "flip": flip / count,
                "mask_iou": hits / union if union else 1.0,
            }
        )

    def frame_rows(self) -> list[dict]:
        """The rows as the report writes them (PSNR to 0.01 dB, FLIP to 1e-4, IoU to 1e-3)."""
        return [
            {**r, "psnr": round(r["psnr"], 2), "flip": round(r["flip"], 4),
             "mask_iou": round(r["mask_iou"], 3)}
            for r in self.rows
        ]  # fmt: skip

    def summary(self) -> dict:
        if not self.pixels:
            return {"frames": 0}
        return {
            "frames": len(self.rows),
            "pixels": self.pixels,
            "psnr": round(_psnr(self.beauty_se / self.pixels), 2),
            "albedo_psnr": round(_psnr(self.albedo_se / self.pixels), 2),
            "median_frame_psnr": round(float(np.median([r["psnr"] for r in self.rows])), 2),
            "flip": round(self.flip_sum / self.pixels, 4),
            "mask_iou": round(self.iou_hits / max(self.iou_union, 1), 3),
            "worst_frame_iou": round(float(min(r["mask_iou"] for r in self.rows)), 3),
        }


def _psnr(mse: float) -> float:
    return float(10 * np.log10(1 / max(mse, 1e-12)))


@dataclass
class Part:
    name: str
    meshes: RegionMeshes
    """The posed meshes cut to the part's triangles (capture/regions.py)."""
    crops: list[tuple[int, float, list[np.ndarray]]] = field(default_factory=list)
    """(pixels, time, [reference crop, each draw's crop]) of the frames shown."""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.regions_report", description=__doc__.split("\n\n")[2]
    )
    parser.add_argument("scene", help="the .usd* shot with one neural character")
    parser.add_argument("--out", required=True, help="folder for the report and the crops")
    parser.add_argument(
        "--draw",
        action="append",
        default=[],
        metavar="LABEL=BUNDLE[:body]",
        help="a model bundle to draw the character with (:body: its body alone); default: the "
        "scene's model with its regions ('regions') and without ('body')",
    )
    parser.add_argument(
        "--part",
        action="append",
        default=[],
        metavar="NAME=JOINT",
        help="a part to measure besides the character's regions: the surface of JOINT and the "
        "joints below it (leftArm=upperarm_l)",
    )
    parser.add_argument("--frames", default=None, help="A:B, default the stage's range")
    parser.add_argument("--step", type=int, default=20, help="every Nth frame (20)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument(
        "--camera", default=None, help="the Camera prim (default: the stage's first)"
    )
    parser.add_argument("--renderer", default="auto", help="the reference's renderer (auto)")
    return parser.parse_args(argv)


def _draws(args: argparse.Namespace) -> list[tuple[str, str | None, bool]]:
    """(label, bundle or None for the scene's own, with regions) per --draw."""
    if not args.draw:
        return [("regions", None, True), ("body", None, False)]
    draws = []
    for text in args.draw:
        label, sep, bundle = text.partition("=")
        if not sep or not label or not bundle:
            raise SystemExit(f"--draw {text!r}: write LABEL=BUNDLE or LABEL=BUNDLE:body")
        body = bundle.endswith(":body")
        bundle = bundle.removesuffix(":body")
        if not (Path(bundle) / "manifest.json").is_file():
            raise SystemExit(f"--draw {text!r}: {bundle} is not a model bundle (no manifest.json)")
        draws.append((label, bundle, not body))
    return draws


def _parts(args: argparse.Namespace, character) -> list[Part]:
    from rigspace.capture.regions import region_joints
    from rigspace.sdk import schema

    regions = list(schema.read_regions(character.prim))
    for text in args.part:
        name, sep, joint = text.partition("=")
        if not sep or not name or not joint:
            raise SystemExit(f"--part {text!r}: write NAME=JOINT (leftArm=upperarm_l)")
        regions.append(schema.Region(name=name, joint=joint))
    if not regions:
        raise SystemExit(
            f"{character.path} declares no region and no --part was given: nothing to measure "
            "(docs/regions.md; or pass --part NAME=JOINT)"
        )
    return [
        Part(r.name, RegionMeshes(character.rig, region_joints(character.rig, r))) for r in regions
    ]


def _frames(args: argparse.Namespace, stage) -> np.ndarray:
    if args.frames:
        a, _, b = args.frames.partition(":")
        start, end = float(a), float(b)
    else:
        start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
    return np.arange(start, end + 1e-6, args.step)


def own_pixels(part_maps, truth_depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: where the part's surface is the nearest thing in the reference frame."""
    from rigspace.capture.regions import VISIBLE_DEPTH

    nearest = np.where(np.isfinite(truth_depth), truth_depth, np.inf)
    return (part_maps.mask >= 0.5) & (part_maps.depth <= nearest * (1.0 + VISIBLE_DEPTH))


def grow(mask: np.ndarray, pixels: int) -> np.ndarray:
    import cv2

    kernel = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


def crop(image: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The square around `near`'s pixels of sRGB `image`, enlarged to CROP_PX (nearest)."""
    import cv2

    from rigspace.sdk.color import linear_to_srgb

    ys, xs = np.nonzero(near)
    side = int(max(np.ptp(ys), np.ptp(xs))) + 1 + 2 * NEAR_PX
    cy, cx = (ys.min() + ys.max()) // 2, (xs.min() + xs.max()) // 2
    h, w = near.shape
    y0 = int(np.clip(cy - side // 2, 0, max(h - side, 0)))
    x0 = int(np.clip(cx - side // 2, 0, max(w - side, 0)))
    square = linear_to_srgb(np.clip(image[y0 : y0 + side, x0 : x0 + side], 0, 1))
    return cv2.resize(square, (CROP_PX, CROP_PX), interpolation=cv2.INTER_NEAREST)


def run(args: argparse.Namespace) -> tuple[dict, list[Part], list[str]]:
    """Every frame measured (module doc): the report, the parts with their crops, the labels."""
    from tqdm import tqdm

    from rigspace.runtime.engine import Engine
    from rigspace.runtime.settings import EngineSettings
    from rigspace.sdk.render import RenderSettings, choose_renderer

    draws = _draws(args)
    size = {"width": args.width, "height": args.height, "camera": args.camera}
    opened: list = []
    try:
        truth = Engine(
            args.scene, EngineSettings(reference=True, renderer=args.renderer, live=False, **size)
        )
        opened.append(truth)
        if len(truth.characters) != 1:
            raise SystemExit(
                f"{args.scene} has {len(truth.characters)} neural characters; one is measured"
            )
        parts = _parts(args, truth.characters[0])
        for _, bundle, regions in draws:
            models = {"": bundle} if bundle else {}
            settings = EngineSettings(live=False, regions=regions, models=models, **size)
            opened.append(Engine(args.scene, settings))
        renderer = choose_renderer(args.renderer).create(RenderSettings(2))
        opened.append(renderer)
        tallies = {(p.name, label): Tally() for p in parts for label, _, _ in draws}
        times = _frames(args, truth.stage)
        for t in tqdm(times, unit="frame", desc="frames"):
            _measure(float(t), truth, opened[1:-1], renderer, parts, [d[0] for d in draws], tallies)
    finally:
        for thing in opened:
            thing.close()
    return (
        {
            "scene": str(args.scene),
            "size": [args.width, args.height],
            "frames": [float(t) for t in times],
            "draws": {
                label: {"bundle": bundle, "regions": regions} for label, bundle, regions in draws
            },
            "parts": {
                p.name: {label: tallies[p.name, label].summary() for label, _, _ in draws}
                for p in parts
            },
            "crops": {p.name: [[n, t] for n, t, _ in p.crops] for p in parts},
            "per_frame": {
                p.name: {label: tallies[p.name, label].frame_rows() for label, _, _ in draws}
                for p in parts
            },
        },
        parts,
        [label for label, _, _ in draws],
    )


def _measure(t: float, truth, engines, renderer, parts, labels, tallies) -> None:
    """One frame: the reference and each draw rendered, each part's pixels measured."""
    from rigspace.sdk.camera import Camera

    reference = truth.render(t)
    frames = [e.render(t) for e in engines]
    camera = Camera.from_usd(truth.camera_prim, t, truth.settings.width, truth.settings.height)
    character = truth.characters[0]
    posed = character.rig.posed_meshes(t, charts=False)
    mesh_cover = truth.coverage_of(character.path, t)
    for part in parts:
        meshes = part.meshes.of(posed)
        if not meshes:
            continue
        own = own_pixels(renderer.render(meshes, camera), reference.maps.depth)
        if own.sum() < MIN_PIXELS:
            continue
        near = grow(own, NEAR_PX)
        for label, engine, frame in zip(labels, engines, frames, strict=True):
            drawn = engine.coverage_of(character.path, t)
            if drawn is None:  # not drawn this frame: it covers nothing
                drawn = np.zeros_like(own, np.float32)
            tallies[part.name, label].add(t, frame, reference, own, near, (drawn, mesh_cover))
        shown = [crop(reference.beauty, near), *(crop(f.beauty, near) for f in frames)]
        part.crops.append((int(own.sum()), t, shown))
        part.crops = sorted(part.crops, key=lambda c: -c[0])[:CROPS]


def table(result: dict) -> str:
    """The report as markdown: a table per part, a row per draw."""
    lines = [
        f"# Parts against the skinned mesh: {result['scene']} at {result['size'][0]}x{result['size'][1]}, "
        f"{len(result['frames'])} frames",
        "",
    ]
    for part, rows in result["parts"].items():
        lines += [
            f"## {part}",
            "",
            "| draw | frames | pixels | beauty PSNR (pooled) | median frame | albedo PSNR | FLIP | mask IoU near it | worst frame IoU |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for label, s in rows.items():
            if not s.get("frames"):
                lines.append(f"| {label} | 0 | | | | | | | |")
                continue
            lines.append(
                f"| {label} | {s['frames']} | {s['pixels']:,} | {s['psnr']:.2f} dB | "
                f"{s['median_frame_psnr']:.2f} dB | {s['albedo_psnr']:.2f} dB | {s['flip']:.4f} | "
                f"{s['mask_iou']:.3f} | {s['worst_frame_iou']:.3f} |"
            )
        lines.append("")
        lines += _spread(result["per_frame"][part])
    return "\n".join(lines)


def _spread(rows: dict[str, list[dict]]) -> list[str]:
    """Markdown: the SPREAD_ROWS frames where the draws' beauty PSNR differ most, every draw's
    PSNR and FLIP in each (none with fewer than two draws)."""
    labels = list(rows)
    by_time: dict[float, dict[str, dict]] = {}
    for label in labels:
        for row in rows[label]:
            by_time.setdefault(row["t"], {})[label] = row
    shared = {t: r for t, r in by_time.items() if len(r) == len(labels)}
    if len(labels) < 2 or not shared:
        return []

    def spread(t: float) -> float:
        values = [shared[t][label]["psnr"] for label in labels]
        return max(values) - min(values)

    worst = sorted(shared, key=lambda t: -spread(t))[:SPREAD_ROWS]
    lines = [
        "Where the draws differ most (beauty PSNR dB / FLIP per frame):",
        "",
        "| frame | pixels | " + " | ".join(labels) + " |",
        "|---" * (len(labels) + 2) + "|",
    ]
    for t in worst:
        cells = [
            f"{shared[t][label]['psnr']:.2f} / {shared[t][label]['flip']:.3f}" for label in labels
        ]
        lines.append(f"| {t:g} | {shared[t][labels[0]]['pixels']} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def plot_frames(rows: dict[str, list[dict]], path: Path, part: str) -> str:
    """Each draw's beauty PSNR over the part's own pixels, frame by frame, as a PNG at `path`;
    "" when written, else why not (fewer than two draws; no matplotlib, the dev extra)."""
    if len(rows) < 2:
        return "one draw: nothing to compare"
    try:
        import matplotlib
    except ImportError:
        return "matplotlib is not installed (pip install matplotlib, or rigspace's dev extra)"
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rigspace.sdk.files import write_atomic

    fig, ax = plt.subplots(figsize=(10, 3.6))
    for label, frames in rows.items():
        ax.plot([r["t"] for r in frames], [r["psnr"] for r in frames], marker=".", label=label)
    ax.set_xlabel("stage frame")
    ax.set_ylabel(f"{part}: beauty PSNR over its own pixels (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    write_atomic(path, buffer.getvalue())
    return ""


def write(out: Path, result: dict, parts: list[Part], labels: list[str]) -> str:
    """The report's files (module doc) in `out`; "" or why the frame plots are not there."""
    import cv2

    from rigspace.sdk.files import write_atomic

    out.mkdir(parents=True, exist_ok=True)
    unplotted = ""
    for part in parts:
        if not part.crops:
            continue
        rows = [np.concatenate(shown, axis=1) for _, _, shown in part.crops]
        sheet = (np.concatenate(rows, axis=0) * 255 + 0.5).astype(np.uint8)[..., ::-1]
        header = np.full((24, sheet.shape[1], 3), 255, np.uint8)
        for k, label in enumerate(["reference", *labels]):
            cv2.putText(
                header, label, (k * CROP_PX + 6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1
            )
        ok, png = cv2.imencode(".png", np.concatenate([header, sheet], axis=0))
        if ok:
            write_atomic(out / f"part_{part.name}.png", png.tobytes())
        unplotted = plot_frames(
            result["per_frame"][part.name], out / f"frames_{part.name}.png", part.name
        )
    write_atomic(out / "regions_report.json", json.dumps(result, indent=1) + "\n")
    write_atomic(out / "regions_report.md", table(result) + "\n")
    return unplotted


def main(argv: list[str] | None = None) -> int:
    from rigspace.sdk.errors import RigspaceError

    args = parse_args(argv)
    try:
        result, parts, labels = run(args)
    except RigspaceError as exc:
        print(f"regions_report: error: {exc}", file=sys.stderr)
        return 1
    unplotted = write(Path(args.out), result, parts, labels)
    print(table(result))
    print(f"wrote {args.out}/regions_report.json, regions_report.md and the part images")
    if unplotted:
        print(f"no frames_NAME.png plots: {unplotted}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

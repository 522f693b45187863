"""`rigspace train` and `rigspace eval`: thin wrappers over train.loop, train.export, train.evaluate.

`python -m rigspace.apps.train DATASET --out MODEL ...` is `rigspace train`, the form torchrun
runs (`--nproc N` spawns it)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rigspace.sdk.cli import CommandSpec
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.predictors import add_device_argument, add_predictor_argument

if TYPE_CHECKING:
    from rigspace.sdk.model import BundleModel
    from rigspace.train.config import TrainConfig
    from rigspace.train.distributed import Context
    from rigspace.train.loop import TrainResult

TRAINING = "training"
"""Subfolder of a model bundle holding the run: run.json, checkpoint.pt, log, previews."""
RUN_FILE = "run.json"
"""train.loop.RUN_FILE (not imported: that module needs torch, and --help must not)."""


def _add_config_flags(parser: argparse.ArgumentParser) -> None:
    from rigspace.train.config import TrainConfig

    group = parser.add_argument_group("training options (override the preset)")
    for f in dataclasses.fields(TrainConfig):
        if f.name == "preset":
            continue
        flag = "--" + f.name.replace("_", "-")
        if f.type in (bool, "bool"):
            group.add_argument(
                flag, action=argparse.BooleanOptionalAction, default=None, help=f.metadata["help"]
            )
        else:
            kind = {"int": int, "float": float}.get(str(f.type), str)
            group.add_argument(flag, type=kind, default=None, help=f.metadata["help"])


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dataset",
        help="a dataset folder written by `rigspace capture`, or its tar shards (`rigspace "
        "dataset pack`), read as a stream",
    )
    parser.add_argument(
        "--out", required=True, help="model bundle folder (training state in its training/)"
    )
    parser.add_argument(
        "--preset",
        default="small",
        help="tiny (seconds), small (the sample model; the default), paper (GPU)",
    )
    _add_budget_arguments(parser)
    _add_bundle_arguments(parser)
    _add_resource_arguments(parser)
    _add_config_flags(parser)


def _add_budget_arguments(parser: argparse.ArgumentParser) -> None:
    """How long the run trains, and whether it goes on from one in --out: --steps | --minutes,
    --resume, --upgrade."""
    budget = parser.add_mutually_exclusive_group()
    budget.add_argument("--steps", type=int, help="stop after this many steps (checkpointed)")
    budget.add_argument("--minutes", type=float, help="stop after this many minutes (checkpointed)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out")
    parser.add_argument(
        "--anneal",
        type=float,
        default=0.0,
        metavar="SHARE",
        help="over the last SHARE (0-1) of this call's run (its --minutes, else its steps) the "
        "learning rate falls along a half cosine to 1/50 of --lr, at the level the run ends at; "
        "with --resume, within the resumed call's budget (0: constant, the default; "
        "docs/training.md)",
    )
    parser.add_argument(
        "--upgrade",
        action="store_true",
        help="bring the finished run in --out up to this rigspace's network (adds the albedo "
        "branch's alpha, or trains it further; only it trains, --steps of them, default 1500), "
        "then re-export",
    )


def _add_bundle_arguments(parser: argparse.ArgumentParser) -> None:
    """What the model bundle in --out gets: --no-int8, --no-regions | --regions-only, --force."""
    parser.add_argument("--no-int8", action="store_true", help="export fp32 graphs only")
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--no-regions",
        action="store_true",
        help="train the body only, not the regions the dataset holds (DATASET/regions/NAME, "
        "from `rigspace capture --regions`); by default each trains after the body into "
        "OUT/regions/NAME, the budget shared by image size",
    )
    which.add_argument(
        "--regions-only",
        action="store_true",
        help="train only the regions the dataset holds, into OUT/regions/NAME beside the body "
        "bundle already in OUT (trained before), which then lists them; the body is not "
        "touched; --minutes is shared by the regions' image sizes",
    )
    parser.add_argument(
        "--region",
        action="append",
        metavar="NAME",
        help="with --regions-only: train this region alone (repeat for several); the bundle's "
        "other regions are kept as they are",
    )
    parser.add_argument(
        "--region-width",
        type=int,
        default=None,
        metavar="N",
        help="conv channels at 4x4 and 8x8 of each region's network (its --base-width; "
        "default the body's): narrower trains more steps a minute and costs less a frame; "
        "the film face lost its hair and lips at half width (docs/regions.md)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="replace a model bundle (and its training run) already in --out; other files "
        "there are kept",
    )


def _add_resource_arguments(parser: argparse.ArgumentParser) -> None:
    """What the run uses of the machine: --no-cache, --resident (the items' memory), --device,
    --nproc."""
    parser.add_argument(
        "--no-cache",
        action="store_true",
        help="read every sample from its EXR each time instead of decoding the dataset once "
        "into DATASET/cache (`rigspace dataset cache`)",
    )
    parser.add_argument(
        "--resident",
        choices=("auto", "on", "off"),
        default="auto",
        help="keep the training items decoded in the device's memory, a batch a gather there "
        "(auto: on a GPU where they fit in half its free memory; on: always; off: never)",
    )
    parser.add_argument(
        "--device",
        default="auto",
        help="where to train: auto (a CUDA GPU when torch sees one, else the CPU), cpu, cuda "
        "or cuda:N; under torchrun each rank takes its LOCAL_RANK's GPU unless cpu",
    )
    parser.add_argument(
        "--nproc",
        type=int,
        default=1,
        help="train on N processes of this machine under torchrun (DDP; --batch stays the "
        "global batch); for several nodes run torchrun yourself (docs/scale.md)",
    )


def _train_config(args: argparse.Namespace) -> TrainConfig:
    """--preset with the training options given on the command line over it."""
    from rigspace.train.config import TrainConfig, preset

    names = [f.name for f in dataclasses.fields(TrainConfig) if f.name != "preset"]
    try:
        return preset(args.preset, **{n: getattr(args, n) for n in names})
    except KeyError as exc:
        raise RigspaceError(str(exc.args[0]), "pass --preset tiny, small or paper.") from None


def _print_result(result: TrainResult, out: Path) -> None:
    """The run's summary line; for an interrupted run, where its checkpoint is."""
    print(
        f"trained {result.step} steps in {result.seconds:.0f} s ({result.images_per_second:.1f} images/s), "
        f"stopped: {result.stopped}, last loss {result.last_loss:.4f}"
    )
    if result.stopped == "interrupted":
        print(
            f"checkpoint saved in {out / TRAINING}; continue with the same command and --resume "
            "(no bundle exported from an interrupted run)"
        )


def run_train(args: argparse.Namespace) -> int:
    from rigspace.capture.dataset import read_manifest
    from rigspace.train import distributed
    from rigspace.train.config import check_anneal

    config = _train_config(args)
    check_anneal(args.anneal)
    out = Path(args.out)
    if args.force and (args.resume or args.upgrade):
        raise RigspaceError(
            "--force starts over and cannot be combined with --resume or --upgrade.",
            "drop --force to continue the run in --out, or drop --resume/--upgrade to replace it.",
        )
    if args.region and not args.regions_only:
        raise RigspaceError(
            "--region picks the regions --regions-only trains.",
            "add --regions-only to train those regions alone beside the body in --out, or drop "
            "--region to train the body and every region.",
        )
    region_training_config(config, config.resolution, args.region_width)  # before the body trains
    if not args.regions_only:  # the body bundle in --out is kept: _regions_only checks it
        check_out(out, resume=args.resume or args.upgrade, force=args.force)
    if args.nproc > 1 and not distributed.under_torchrun():
        return launch(args, args.nproc)
    from rigspace.train.loop import train  # torch: after the launch, which needs none

    ctx = distributed.context(args.device)  # under torchrun: joins the process group
    if args.upgrade:
        return _upgrade(args, out)
    if args.regions_only:
        return _regions_only(args, out, config, ctx)
    body = read_manifest(Path(args.dataset))  # a bad dataset fails before --force removes anything
    regions = [] if args.no_regions else region_datasets(Path(args.dataset))
    shares = budget_shares(body.resolution, [r for _, r in regions], args.minutes)
    if args.force and ctx.is_main:
        removed = clear_bundle(out)
        if removed:
            print(f"--force: removed {len(removed)} files of the bundle in {out}", file=sys.stderr)
    ctx.barrier()
    result = train(
        args.dataset,
        out / TRAINING,
        config,
        steps=args.steps,
        minutes=shares[0],
        resume=args.resume,
        device=args.device,
        cache=not args.no_cache,
        resident=args.resident,
        anneal=args.anneal,
    )
    if not ctx.is_main:  # rank 0 reports and exports; the others wait for it
        if result.stopped == "interrupted":
            return 130
        ctx.barrier()
        return _train_regions(args, out, config, regions, shares[1:], ctx) if regions else 0
    _print_result(result, out)
    if result.stopped == "interrupted":
        return 130
    code = _export(args, out)
    ctx.barrier()
    if code == 0 and regions:
        code = _train_regions(args, out, config, regions, shares[1:], ctx)
    return code


REGIONS = "regions"
"""Subfolder of a dataset (capture --regions) and of a model bundle holding its regions."""


def region_datasets(dataset: Path) -> list[tuple[str, int]]:
    """(name, resolution) of each region dataset in DATASET/regions (capture --regions), by
    name; each one's manifest is read (a damaged one fails here, before anything trains)."""
    from rigspace.capture.dataset import MANIFEST_FILE, read_manifest

    folder = dataset / REGIONS
    if not dataset.is_dir() or not folder.is_dir():
        return []
    found = sorted(p for p in folder.iterdir() if (p / MANIFEST_FILE).is_file())
    return [(p.name, read_manifest(p).resolution) for p in found]


def region_training_config(config: TrainConfig, resolution: int, width: int | None) -> TrainConfig:
    """A region's training options: the body's at the region's resolution, its network
    `width` channels at 4x4 and 8x8 (None: the body's base_width; docs/regions.md)."""
    if width is not None and width < 1:
        raise RigspaceError(
            f"--region-width is {width}.", "pass a number of channels of 1 or more (e.g. 64)."
        )
    base = config.base_width if width is None else width
    return dataclasses.replace(
        config,
        resolution=resolution,
        start_resolution=min(config.start_resolution, resolution),
        base_width=base,
    )


def budget_shares(body: int, regions: Sequence[int], minutes: float | None) -> list[float | None]:
    """--minutes split between the body and its regions in proportion to their images'
    pixels (a step's cost grows with them), so each trains about as many steps; None for
    each without --minutes."""
    if minutes is None:
        return [None] * (1 + len(regions))
    pixels = [body * body, *(r * r for r in regions)]
    return [minutes * p / sum(pixels) for p in pixels]


def _regions_only(args: argparse.Namespace, out: Path, config: TrainConfig, ctx: Context) -> int:
    """--regions-only: the dataset's regions trained into OUT/regions/NAME beside the body
    bundle already in OUT, which is left as it is but for its manifest's list of regions."""
    if args.upgrade:
        raise RigspaceError(
            "--regions-only trains new region networks; --upgrade brings a finished run up "
            "to date.",
            "pass one of them.",
        )
    if not (out / "manifest.json").is_file():
        raise RigspaceError(
            f"--regions-only adds regions to the body bundle in --out, and {out} holds none "
            "(no manifest.json).",
            "train the body first (rigspace train DATASET --out OUT --no-regions), or drop "
            "--regions-only to train the body and its regions together.",
        )
    regions = region_datasets(Path(args.dataset))
    if not regions:
        raise RigspaceError(
            f"{args.dataset} holds no region datasets ({REGIONS}/NAME), so --regions-only has "
            "nothing to train.",
            "capture them: rigspace capture SCENE --out DATASET --regions (or --region NAME "
            "--out DATASET/regions/NAME).",
        )
    if args.region:
        held = [name for name, _ in regions]
        missing = [name for name in args.region if name not in held]
        if missing:
            raise RigspaceError(
                f"--region {', '.join(missing)}: {args.dataset} holds no such region dataset "
                f"(it holds {', '.join(held)}).",
                "name a region it holds, or capture it: rigspace capture SCENE --region NAME "
                "--out DATASET/regions/NAME.",
            )
        regions = [r for r in regions if r[0] in args.region]
    for name, _ in regions:
        home = out / REGIONS / name
        check_out(home, resume=args.resume, force=args.force)
        if (home / TRAINING / RUN_FILE).is_file() and not (args.resume or args.force):
            raise RigspaceError(
                f"region {name} was trained into {home} before (its run is there).",
                "pass --resume to continue it, or --force to train it anew.",
            )
        if args.force and ctx.is_main:
            clear_bundle(home)
    ctx.barrier()
    shares = budget_shares(0, [r for _, r in regions], args.minutes)[1:]
    return _train_regions(args, out, config, regions, shares, ctx)


def _train_regions(
    args: argparse.Namespace,
    out: Path,
    config: TrainConfig,
    regions: list[tuple[str, int]],
    shares: list[float | None],
    ctx: Context,
) -> int:
    """Each region's network on its dataset into OUT/regions/NAME (a bundle of its own, with
    its own training run), then the body's manifest lists them."""
    from rigspace.sdk.bundle import read_manifest_document, write_manifest_document
    from rigspace.train.loop import train

    done = []
    for (name, resolution), minutes in zip(regions, shares, strict=True):
        home = out / REGIONS / name
        region_config = region_training_config(config, resolution, args.region_width)
        print(f"region {name}: training at {resolution}x{resolution} into {home}")
        resume = args.resume and (home / TRAINING / RUN_FILE).is_file()
        result = train(
            Path(args.dataset) / REGIONS / name, home / TRAINING, region_config,
            steps=args.steps, minutes=minutes, resume=resume, device=args.device,
            cache=not args.no_cache, resident=args.resident, anneal=args.anneal,
        )  # fmt: skip
        if not ctx.is_main:
            if result.stopped == "interrupted":
                return 130
            ctx.barrier()
            continue
        print(
            f"region {name}: trained {result.step} steps in {result.seconds:.0f} s "
            f"({result.images_per_second:.1f} images/s), stopped: {result.stopped}"
        )
        if result.stopped == "interrupted":
            print(
                f"checkpoint saved in {home / TRAINING}; continue with the same command and "
                "--resume (the body's bundle is exported, without its regions yet)"
            )
            return 130
        _export(args, home)
        done.append(name)
        ctx.barrier()
    if ctx.is_main:
        document = read_manifest_document(out)
        listed = {r["name"]: r for r in document.get(REGIONS, [])}
        for name in done:
            joint = read_manifest_document(out / REGIONS / name).get("look_at_joint", "")
            listed[name] = {"name": name, "joint": joint, "bundle": f"{REGIONS}/{name}"}
        document[REGIONS] = [listed[n] for n in sorted(listed)]
        write_manifest_document(out, document)
        print(f"regions in {out}: {', '.join(sorted(listed))}")
    return 0


def _listed_regions(out: Path) -> list[dict]:
    """The regions the bundle in `out` lists whose bundles are still there: a body exported
    again over it (--resume, --upgrade) lists them too: the export writes a new manifest.
    Empty where it lists none or its manifest cannot be read."""
    from rigspace.sdk.bundle import BundleError, read_manifest_document

    if not (out / "manifest.json").is_file():
        return []
    try:
        listed = read_manifest_document(out).get(REGIONS) or []
    except BundleError:
        return []
    return [
        r for r in listed
        if isinstance(r, dict) and isinstance(r.get("bundle"), str)
        and (out / r["bundle"] / "manifest.json").is_file()
    ]  # fmt: skip


def _export(args: argparse.Namespace, out: Path, metrics: dict | None = None) -> int:
    """Export the run in out/training, then say what the bundle holds and what failed."""
    from rigspace.train.export import export_bundle
    from rigspace.train.int8check import failure_lines

    listed = _listed_regions(out)
    manifest = export_bundle(out / TRAINING, out, int8=not args.no_int8, metrics=metrics)
    if listed:  # a body exported again (--resume, --upgrade) keeps its regions listed
        from rigspace.sdk.bundle import write_manifest_document

        manifest[REGIONS] = listed  # the document export_bundle just wrote
        write_manifest_document(out, manifest)
    graphs = [name for name in manifest["files"] if name.endswith(".onnx")]
    size = sum(v["bytes"] for v in manifest["files"].values())
    training = manifest["training"]
    levels = ", ".join(str(r) for r in training["trained_levels"])
    print(
        f"exported {len(graphs)} graphs ({size / 2**20:.1f} MiB) to {out}: levels {levels}"
        + (", capsules" if "capsules" in manifest else "")
    )
    if training["trained_levels"] != training["planned_levels"]:
        final = training["planned_levels"][-1]
        print(
            f"rigspace train: warning: the run stopped at step {training['steps']} of "
            f"{training['planned_steps']}, before level {final} was trained: the bundle holds "
            f"levels up to {training['trained_levels'][-1]} only; continue with the same "
            "command and --resume to train the rest",
            file=sys.stderr,
        )
    for line in failure_lines(manifest.get("int8_check", {})):
        print(f"rigspace train: warning: {line}", file=sys.stderr)
    return 0


def check_out(out: Path, resume: bool, force: bool) -> None:
    """Refuse an --out that is a file, or that holds a bundle this run would not continue."""
    check_folder(out, "--out")
    if force or not out.is_dir() or (out / TRAINING / RUN_FILE).is_file():
        return
    found = bundle_files(out)
    if found:
        what = "a model bundle" if (out / "manifest.json").is_file() else "model graphs"
        raise RigspaceError(
            f"--out {out} holds {what} ({len(found)} files) without its training run "
            f"({TRAINING}/{RUN_FILE}), so "
            + ("there is nothing to continue." if resume else "training would mix with it."),
            "choose a new --out, or pass --force to replace that bundle.",
        )


def check_folder(path: Path, flag: str) -> None:
    """An output folder `flag` names must be a folder, or creatable: checked before any work."""
    if path.exists() and not path.is_dir():
        raise RigspaceError(f"{flag} {path} is a file.", f"give {flag} a folder.")
    parent = next(p for p in [path, *path.parents] if p.exists())
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise RigspaceError(
            f"{flag} {path} cannot be written: {parent} is not a writable folder.",
            "choose a writable location.",
        )


def bundle_files(out: Path) -> list[Path]:
    """The files of a model bundle in `out`: its manifest, what it lists, and graphs."""
    manifest = out / "manifest.json"
    names = {p.name for p in out.glob("*.onnx")} | {"capsules.json"}
    if manifest.is_file():
        names.add(manifest.name)
        try:
            listed = json.loads(manifest.read_text()).get("files", {})
            names |= {n for n in listed if isinstance(n, str) and "/" not in n}
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
            pass  # a damaged manifest: its graphs are still found by name
    return sorted(out / n for n in names if (out / n).is_file())


def clear_bundle(out: Path) -> list[Path]:
    """--force: remove the bundle in `out` (its files and training run); nothing else there."""
    import shutil

    removed = bundle_files(out) if out.is_dir() else []
    for path in removed:
        path.unlink()
    if (out / TRAINING).is_dir():
        shutil.rmtree(out / TRAINING)
        removed.append(out / TRAINING)
    if (out / REGIONS).is_dir():  # the regions' bundles and runs (written by train alone)
        shutil.rmtree(out / REGIONS)
        removed.append(out / REGIONS)
    return removed


def _upgrade(args: argparse.Namespace, out: Path) -> int:
    from rigspace.train.upgrade import upgrade

    old = out / "manifest.json"
    metrics = json.loads(old.read_text()).get("metrics", {}) if old.is_file() else {}
    result = upgrade(args.dataset, out / TRAINING, steps=args.steps or 1500)
    print(
        f"upgraded: alpha heads trained in {result.seconds:.0f} s "
        f"({result.images_per_second:.1f} images/s), last alpha loss {result.last_loss:.4f}"
    )
    # Every other output is bit-identical, so the recorded metrics still hold.
    return _export(args, out, metrics)


def torchrun_argv(args: argparse.Namespace, nproc: int) -> list[str]:
    """The torchrun command that runs `rigspace train` with `args` on `nproc` local ranks."""
    from rigspace.train.config import TrainConfig

    argv = [str(args.dataset), "--out", str(args.out), "--preset", args.preset]
    if args.steps is not None:
        argv += ["--steps", str(args.steps)]
    if args.minutes is not None:
        argv += ["--minutes", repr(args.minutes)]
    if getattr(args, "anneal", 0.0):
        argv += ["--anneal", repr(args.anneal)]
    argv += [f"--{f.replace('_', '-')}" for f in ("resume", "no_int8", "force") if getattr(args, f)]
    if getattr(args, "device", None):
        argv += ["--device", str(args.device)]
    for f in TrainConfig.__dataclass_fields__.values():
        value = getattr(args, f.name, None)
        if f.name == "preset" or value is None:
            continue
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, bool):
            argv.append(flag if value else "--no-" + f.name.replace("_", "-"))
        else:
            argv += [flag, str(value)]
    return [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        f"--nproc-per-node={nproc}",
        "-m",
        "rigspace.apps.train",
        *argv,
    ]


def launch(args: argparse.Namespace, nproc: int) -> int:
    """`rigspace train --nproc N`: run the same training under torchrun; its exit code."""
    if args.upgrade:
        raise RigspaceError(
            "--upgrade trains a few heads on one process and cannot run with --nproc.",
            "drop --nproc for --upgrade.",
        )
    return subprocess.run(torchrun_argv(args, nproc), check=False).returncode


TRAIN_COMMAND = CommandSpec(
    name="train",
    help="train a Rig2Image model on a capture dataset and export its bundle",
    description=(
        "Train the Rig2Image network progressively (16x16 first, then one block at a time with a\n"
        "linear fade-in) on a dataset from `rigspace capture`, then export the model bundle:\n"
        "a shared trunk graph and one ONNX graph per (branch, level), static int8 variants,\n"
        "manifest.json. Ctrl-C stops with a usable checkpoint; --resume continues exactly."
    ),
    add_arguments=add_train_arguments,
    run=run_train,
)


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="a model bundle folder")
    parser.add_argument("dataset", help="a dataset folder written by `rigspace capture`")
    parser.add_argument(
        "--split", default="heldout-views", help="heldout-views, heldout-clips or train"
    )
    parser.add_argument(
        "--limit", type=int, default=200, help="samples evaluated (evenly spaced; 0: all)"
    )
    parser.add_argument("--int8", action="store_true", help="evaluate the int8 graphs")
    add_predictor_argument(parser)
    add_device_argument(parser)
    parser.add_argument(
        "--no-baselines", action="store_true", help="skip nearest-view and interpolation"
    )
    parser.add_argument("--errors", help="folder for error-map images of the worst samples")
    parser.add_argument(
        "--shapes",
        nargs="*",
        metavar="SHAPE",
        help="also measure the shape response: each blend shape's weight 0 -> 1 with the pose "
        "and camera held, the network's albedo change against the mesh's (ratio, correlation) "
        "on --shape-samples samples of --split; no names: every shape the model reads "
        "(train/shapes.py)",
    )
    parser.add_argument(
        "--shape-samples",
        type=int,
        default=8,
        metavar="N",
        help="samples of --split the shape response is measured on, evenly spaced (default 8; "
        "each renders the mesh twice per shape)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--record", action="store_true", help="store the model's metrics in the bundle manifest"
    )
    parser.add_argument(
        "--display",
        action="store_true",
        help="measure at the size the character is seen: on a dataset captured above the "
        "model's resolution (capture --resolution 512 --every 10), at 2x, 4x, ... the model's "
        "resolution up to the dataset's, the model as `rigspace render` draws it (textures, "
        "sharpened coverage) against the albedo branch, plain bilinear upsampling and the truth "
        "at the model's resolution upsampled",
    )


def _record_display(args: argparse.Namespace, results: dict[int, dict[str, Any]]) -> None:
    """--record: the display results, by split and size, in the bundle manifest's metrics."""
    from rigspace.sdk.bundle import read_manifest_document, write_manifest_document
    from rigspace.train.evaluate import to_json

    manifest = read_manifest_document(args.model)
    display = manifest.setdefault("metrics", {}).setdefault("display", {})
    for size, result in results.items():
        display.setdefault(args.split, {})[str(size)] = json.loads(
            to_json({"samples": result["samples"], "rows": result["rows"]})
        )
    write_manifest_document(args.model, manifest)


def run_display(args: argparse.Namespace) -> int:
    """`rigspace eval --display` (train/display.py)."""
    from rigspace.sdk.model import BundleModel
    from rigspace.train.data import chart_boxes
    from rigspace.train.display import (
        MODES,
        DisplayPredictor,
        TrueCoordinates,
        UpsampledTruth,
        display_sizes,
        scene_textures,
    )
    from rigspace.train.evaluate import DatasetTable, compare, format_table, to_json

    full = DatasetTable(Path(args.dataset))
    model = BundleModel(
        Path(args.model),
        "int8" if args.int8 else "fp32",
        predictor=args.predictor,
        device=args.device,
    )
    level = max(model.resolutions)
    warn_damaged_graphs(Path(args.model), model, level)
    sizes = display_sizes(level, full.resolution)
    if not sizes:
        raise RigspaceError(
            f"--display: {args.dataset} is captured at {full.resolution}x{full.resolution}, not "
            f"above the model's {level}x{level}.",
            f"capture a small evaluation set at 2x or 4x: `rigspace capture SCENE --out DIR "
            f"--resolution {4 * level} --every 10`.",
        )
    textures, why = scene_textures(model, full.manifest)
    if why:
        print(f"note: runtime colour is the albedo branch: {why}", file=sys.stderr)
    boxes = chart_boxes(Path(args.dataset)) if textures is not None else None
    results = {}
    for size in sizes:
        table = DatasetTable(Path(args.dataset), size)
        predictors = [DisplayPredictor(model, table, mode, textures) for mode in MODES]
        predictors.append(UpsampledTruth(table, level))
        if textures is not None and boxes is not None:
            predictors.append(TrueCoordinates(table, level, textures, boxes))
        out_dir = Path(args.errors) / f"display_{size}" if args.errors else None
        result = compare(predictors, table, args.split, limit=args.limit or None, out_dir=out_dir)
        results[size] = result
        if not args.json:
            print(f"at {size}x{size} ({size // level}x the model's {level}x{level}):")
            print(format_table(result))
    if args.record:
        _record_display(args, results)
    if args.json:
        sys.stdout.write(to_json({str(k): v for k, v in results.items()}))
    return 0


def run_eval(args: argparse.Namespace) -> int:
    from rigspace.sdk.bundle import read_manifest as read_bundle
    from rigspace.train.evaluate import format_table, to_json

    if args.errors:
        check_folder(Path(args.errors), "--errors")  # before the evaluation, not after it
    if args.shape_samples < 1:
        raise RigspaceError(
            f"--shape-samples is {args.shape_samples}.", "pass 1 or more samples (default 8)."
        )
    if args.display:
        return run_display(args)
    model, dataset = Path(args.model), Path(args.dataset)
    result = _evaluate(args, model, dataset, Path(args.errors) if args.errors else None)
    regions = {}
    for region in read_bundle(model).regions:  # each region's network on its own dataset
        data = dataset / REGIONS / region.name
        if not (data / "manifest.json").is_file():
            _note(
                f"region {region.name} is not measured: {dataset} has no {REGIONS}/{region.name} "
                "(capture it with `rigspace capture SCENE --out DATASET --regions`)"
            )
            continue
        errors = Path(args.errors) / REGIONS / region.name if args.errors else None
        regions[region.name] = _evaluate(args, region.folder, data, errors)
        if args.shapes is not None:
            regions[region.name]["shapes"] = _shapes(args, region.folder, data)
    if args.shapes is not None:
        result["shapes"] = _shapes(args, model, dataset)
    if args.json:  # strict JSON: null for nan and inf, never NaN
        sys.stdout.write(to_json(result | ({"regions": regions} if regions else {})))
        return 0
    print(format_table(result) + _shapes_table(result, "the model"))
    for name, region_result in regions.items():
        print(f"region {name} ({model / REGIONS / name} on {dataset / REGIONS / name}):")
        print(format_table(region_result) + _shapes_table(region_result, f"region {name}"))
    return 0


def _shapes(args: argparse.Namespace, model: Path, dataset: Path) -> list[dict]:
    """--shapes for one bundle on its dataset: the shapes it reads among those named."""
    from rigspace.sdk.bundle import read_manifest as read_bundle
    from rigspace.train.shapes import shape_response

    read = read_bundle(model).blend_shapes
    if not read:
        _note(f"{model} reads no blend shapes: no shape response")
        return []
    names = [s for s in args.shapes if s in read] if args.shapes else list(read)
    if args.shapes and len(names) < len(args.shapes):
        missing = ", ".join(s for s in args.shapes if s not in read)
        _note(f"{model} does not read {missing}: not measured there")
    if not names:
        return []
    rows = shape_response(
        model, dataset, names, args.split, args.shape_samples, args.predictor, args.device
    )
    return [dataclasses.asdict(r) for r in rows]


def _shapes_table(result: dict, what: str) -> str:
    from rigspace.train.shapes import ShapeResponse, format_responses

    rows = result.get("shapes")
    return "\n" + format_responses([ShapeResponse(**r) for r in rows], what) if rows else ""


def _note(text: str) -> None:
    print(f"note: {text}", file=sys.stderr)


def _evaluate(args: argparse.Namespace, model: Path, dataset: Path, errors: Path | None) -> dict:
    """One bundle against one dataset: the compare() result (recorded in the bundle with
    --record)."""
    from rigspace.train.evaluate import DatasetTable, Downsampled, compare, targets_note
    from rigspace.train.predictor import BundlePredictor
    from rigspace.train.regions import dataset_regions

    table = DatasetTable(dataset)
    top, stopped = model_top_level(model)
    if stopped:
        _note(stopped)
    if top is not None and table.resolution > top and table.resolution % top == 0:
        # The bundle's top level is below the capture's resolution (a model designed so, or a
        # run a budget stopped early): evaluate it there, as the runtime uses it, against
        # box-downsampled targets.
        table = DatasetTable(dataset, top)
        _note(f"targets {targets_note(table)}")
    predictors = [
        BundlePredictor(model, table, int8=args.int8, predictor=args.predictor, device=args.device)
    ]
    warn_damaged_graphs(model, predictors[0].model, table.resolution)
    print(f"the model runs on {predictors[0].model.runner.description}", file=sys.stderr)
    if predictors[0].model.charts:  # the texture head's placement, in texels of the textures
        from rigspace.train.display import scene_textures

        textures, why = scene_textures(predictors[0].model, table.manifest)
        if textures is not None:
            predictors[0].attach_textures(textures)
        else:
            _note(f"the texture head's placement is not measured: {why}")
    if args.split == "heldout-clips" and not args.no_baselines:
        # Held-out clips were never captured from training views: nothing to interpolate.
        _note(
            "the captured-view baselines need training views of the same frame; a held-out "
            "clip has none, so only the model is measured"
        )
    elif not args.no_baselines:
        from rigspace.train.baselines import BaselinePredictor

        predictors += [
            Downsampled(BaselinePredictor(dataset, kind), table.factor)
            for kind in ("nearest", "linear")
        ]
    regions = dataset_regions(json.loads((table.folder / "capture.json").read_text()), _note)
    result = compare(
        predictors, table, args.split, limit=args.limit or None, out_dir=errors, regions=regions
    )
    _warn_draws_nothing(result, predictors[0].name)
    if args.record:
        fallbacks = sorted(predictors[0].model.int8_fallbacks)
        record_metrics(model, args.split, "int8" if args.int8 else "fp32", result, fallbacks)
    return result


def _warn_draws_nothing(result: dict, name: str) -> None:
    """Say when the model's mask is empty on every sample (train.evaluate.draws_nothing)."""
    from rigspace.train.evaluate import draws_nothing

    said = draws_nothing(result["reports"][name])
    if said:
        print(f"rigspace eval: warning: the {said}", file=sys.stderr)


def warn_damaged_graphs(model: Path, loaded: BundleModel, resolution: int) -> None:
    """eval loads one level; a missing or damaged graph of another one (which the runtime
    loads when the character is drawn at that size) is said before the measurement, not left
    for the next render to find. What eval measures (the trunk and the level at `resolution`)
    is loaded first: a problem there, like a manifest eval cannot read, is eval's own error,
    said once (not also as this warning)."""
    from rigspace.sdk.model import graphs_problem

    loaded.preload([resolution])
    if (model / "manifest.json").is_file():
        problem = graphs_problem(model)
        if problem:
            print(
                f"rigspace eval: warning: {problem} (eval measures the levels it loads; "
                "`rigspace render` and inspect refuse the bundle until it is fixed)",
                file=sys.stderr,
            )


def model_top_level(model: Path) -> tuple[int | None, str]:
    """The highest level a bundle has (the runtime's top level), and a sentence when its run
    stopped before the level it planned (a budget); (None, "") when the manifest does not
    say (BundlePredictor then reports the bundle's own problem)."""
    try:
        raw = json.loads((model / "manifest.json").read_text())
        top = int(max(level["resolution"] for level in raw["levels"]))
        training = raw.get("training", {})
        planned = max(training.get("planned_levels") or [top])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None, ""
    if planned <= top:
        return top, ""
    return top, (
        f"the run stopped at step {training.get('steps')} of {training.get('planned_steps')}, "
        f"before level {planned} was trained: the model is measured at its top level {top}, "
        f"as the runtime draws it (train the rest: `rigspace train DATASET --out {model} "
        "--resume`, with the original options)"
    )


def record_metrics(
    model: Path, split: str, precision: str, result: dict, fp32_in_place: Sequence[str] = ()
) -> None:
    """Write the evaluation's aggregated rows into the bundle manifest's metrics (with the
    int8 graphs whose fp32 graphs ran in their place, failed at export, when there are any)."""
    from rigspace.sdk.bundle import read_manifest_document, write_manifest_document
    from rigspace.train.evaluate import to_json

    manifest = read_manifest_document(model)
    rows = json.loads(to_json({"samples": result["samples"], "rows": result["rows"]}))
    if fp32_in_place:
        rows["fp32_in_place_of"] = list(fp32_in_place)
    manifest.setdefault("metrics", {}).setdefault(split, {})[precision] = rows
    write_manifest_document(model, manifest)


EVAL_COMMAND = CommandSpec(
    name="eval",
    help="measure a model bundle on a dataset split against the captured-view baselines",
    add_arguments=add_eval_arguments,
    run=run_eval,
)


if __name__ == "__main__":
    from rigspace.sdk.cli import main

    sys.exit(main(["train", *sys.argv[1:]]))

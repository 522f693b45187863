"""The GPU check: the project's own code on a CUDA machine, in one command of a few minutes.

    python -m rigspace.apps.gpu_check --out gpu_check.json [--dataset DATASET]

Parts (each bounded; a part that cannot run says why and the others go on):

    step        the sample recipe's training step (train.step: network, loss, Adam) at
                128x128 on batches of the real shapes already on the GPU: images/s for batch
                16, 64 and 256, fp32 and bf16 (the arithmetic's ceiling)
    predictors  the torch predictor (fp16, CUDA graphs) on bundles of the sample model's
                architecture at 128, 256 and 512 (random weights: the time does not depend
                on them): ms per character for one character and for eight in one batch;
                onnxruntime-cuda on the sample bundle where onnxruntime-gpu is installed
    train       `rigspace train` itself (train.loop.train) on --dataset through its decoded
                cache, at 128x128, batch 256, bf16: images/s end to end with real data
    frames      a whole 1920x1080 frame of the previs shot with 1 and 8 characters (the
                Engine, --predictor auto): ms per frame and per stage

`step` and `predictors` need only torch and numpy (no usd-core, no OpenImageIO); `train` and
`frames` need rigspace's full install (usd-core and OpenImageIO: on a machine without them,
install their wheels, `pip install usd-core OpenImageIO`). Prints a Markdown table; --out
writes every number as JSON, after each part (a part that runs out of time keeps the others).

On a GPU machine, the whole check: capture the sample dataset there first (the gl renderer
on the GPU's EGL took 60 s for all 49,920 samples on an H200 with 16 workers), then

    rigspace capture samples/scenes/previs.usda --out /tmp/ds --workers 16
    python -m rigspace.apps.gpu_check --out gpu_check.json --dataset /tmp/ds

With the defaults it should take about 3 minutes on such a machine (estimated, not yet run on
a GPU: the step part's 6 timings of 4 s, 6 predictor timings, the train part's cache build and
300 steps, 16 frames at 1080p), inside the 8 minutes asked.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.sdk.files import write_atomic

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "models" / "sample"
PREVIS = ROOT / "samples" / "scenes" / "previs.usda"
BATCHES = (16, 64, 256)
RESOLUTIONS = (128, 256, 512)


def machine() -> dict[str, Any]:
    info: dict[str, Any] = {"python": platform.python_version(), "cpu": platform.processor()}
    try:
        import torch

        info["torch"] = torch.__version__
        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name()
            info["cuda"] = torch.version.cuda
    except ImportError:
        info["torch"] = None
    try:
        import onnxruntime as ort

        info["onnxruntime"] = [ort.__version__, ort.get_available_providers()]
    except ImportError:
        info["onnxruntime"] = None
    return info


def sample_recipe() -> tuple[Any, Any]:
    """(TrainConfig, Shape) of the committed sample model, from its manifest (no dataset)."""
    from rigspace.train.config import TrainConfig
    from rigspace.train.network import Shape

    section = json.loads((SAMPLE / "manifest.json").read_text())["torch"]
    config = TrainConfig.from_json(section["config"])
    shape = Shape(
        int(section["joints"]),
        parents=tuple(section["parents"]),
        charts=int(section["charts"]),
        blend_shapes=int(section.get("blend_shapes", 0)),
        controls=int(section.get("controls", 0)),
    )
    return config, shape


def synthetic_batch(config, shape, batch: int, resolution: int, device) -> dict[str, Any]:
    """A batch of the real shapes and value ranges (rig rotations near rest, coverage in a
    disc, unit normals, charts and uv), made on `device`."""
    import torch

    g = torch.Generator(device="cpu").manual_seed(0)
    rest = torch.tensor([1.0, 0, 0, 0, 1, 0]).repeat(batch, shape.joints)
    rig = rest + 0.1 * torch.randn(rest.shape, generator=g)
    yy, xx = torch.meshgrid(
        torch.linspace(-1, 1, resolution), torch.linspace(-1, 1, resolution), indexing="ij"
    )
    disc = ((yy**2 + xx**2) < 0.5).float()[None, None].expand(batch, 1, -1, -1).contiguous()
    normal = torch.nn.functional.normalize(
        torch.randn(batch, 3, resolution, resolution, generator=g), dim=1
    )
    out = {
        "rig": rig,
        "albedo": torch.rand(batch, 3, resolution, resolution, generator=g) * disc,
        "mask": disc,
        "normal": normal * disc,
        "depth": 0.3 * torch.randn(batch, 1, resolution, resolution, generator=g) * disc,
    }
    if config.conditioning != "none":
        out["joints2d"] = torch.rand(batch, 2 * shape.joints, generator=g) * 1.6 - 0.8
    if config.texture and shape.charts:
        chart = torch.randint(1, shape.charts + 1, (batch, 1, resolution, resolution), generator=g)
        out["chart"] = (chart * disc.long()).long()
        out["uv"] = (torch.rand(batch, 2, resolution, resolution, generator=g) * 2 - 1) * disc
    return {k: v.to(device) for k, v in out.items()}


def part_step(
    device: str, seconds: float, batches: tuple[int, ...] = BATCHES
) -> list[dict[str, Any]]:
    """Images/s of train.step at 128x128 (fade-in done) per batch size, fp32 and bf16."""
    import torch

    from rigspace.train.network import Rig2Image
    from rigspace.train.step import forward_loss, make_optimizer, optimise

    config, shape = sample_recipe()
    rows = []
    for bf16 in (False, True):
        for batch in batches:
            cfg = replace(config, batch=batch, bf16=bf16, lr=config.lr * (batch / 16) ** 0.5)
            torch.manual_seed(0)
            model = Rig2Image(shape, cfg).to(device).to(memory_format=torch.channels_last)
            optimizer = make_optimizer(model, cfg)
            data = synthetic_batch(cfg, shape, batch, cfg.resolution, device)

            def step(model=model, optimizer=optimizer, data=data, cfg=cfg) -> float:
                loss, _ = forward_loss(model, data, cfg.resolution, 1.0, cfg)
                optimise(model, optimizer, loss, cfg)
                return float(loss.detach())

            steps, elapsed, loss = _run_for(step, seconds, device)
            rows.append(
                {
                    "batch": batch,
                    "bf16": bf16,
                    "images_per_s": steps * batch / elapsed,
                    "ms_per_step": 1e3 * elapsed / steps,
                    "last_loss": loss,
                    "finite": bool(np.isfinite(loss)),
                }
            )
    return rows


def _run_for(step: Callable[[], float], seconds: float, device: str) -> tuple[int, float, float]:
    """Warm up (3 steps), then run `step` for about `seconds`; (steps, elapsed, last value)."""
    import torch

    for _ in range(3):
        value = step()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    start, steps = time.perf_counter(), 0
    while time.perf_counter() - start < seconds:
        value = step()
        steps += 1
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return steps, time.perf_counter() - start, value


def synthetic_bundle(folder: Path, resolution: int) -> Path:
    """A bundle of the sample model's architecture up to `resolution` (random weights, torch
    only: no ONNX graphs), for timing the torch predictor above 128."""
    import torch

    from rigspace.sdk.bundle import write_manifest_document
    from rigspace.sdk.weights import write_safetensors
    from rigspace.train.network import TRUNK, Rig2Image

    config, shape = sample_recipe()
    config = replace(config, resolution=resolution)
    torch.manual_seed(0)
    model = Rig2Image(shape, config)
    manifest = json.loads((SAMPLE / "manifest.json").read_text())
    levels, r = [], TRUNK
    while r <= resolution:
        graphs = {b: f"{b}_{r}.onnx" for b in model.branch_names}
        levels.append({"resolution": r, "graphs": graphs, "int8": {}})
        r *= 2
    manifest |= {"levels": levels, "files": {}}
    manifest.pop("int8_check", None)
    manifest["torch"] = {k: v for k, v in manifest["torch"].items() if k != "check"}
    manifest["torch"]["config"] = config.to_json()
    manifest["torch"]["file"] = "weights.safetensors"  # no ONNX graphs to read them from
    out = folder / f"synthetic_{resolution}"
    out.mkdir(parents=True, exist_ok=True)
    write_safetensors(
        out / "weights.safetensors", {k: v.numpy() for k, v in model.state_dict().items()}
    )
    write_manifest_document(out, manifest)
    return out


def part_predictors(
    device: str, repeats: int, folder: Path, resolutions: tuple[int, ...] = RESOLUTIONS
) -> list[dict[str, Any]]:
    """ms per character of the torch predictor at 128/256/512 (and onnxruntime-cuda at 128)."""
    from rigspace.bench.predictors import sample_rigs, time_model
    from rigspace.sdk.errors import RigspaceError
    from rigspace.sdk.model import BundleModel

    rows: list[dict[str, Any]] = []
    for resolution in resolutions:
        bundle = synthetic_bundle(folder, resolution)
        model = BundleModel(bundle, predictor="torch", device=device)
        rigs = sample_rigs(len(model.joints), 8)
        for row in time_model(model, rigs, [resolution], repeats):
            rows.append(
                {"predictor": "torch", "bundle": f"sample architecture at {resolution}", **row}
            )
    try:
        model = BundleModel(SAMPLE, predictor="onnxruntime-cuda", device=device)
    except RigspaceError as exc:
        rows.append({"predictor": "onnxruntime-cuda", "skipped": exc.what})
    else:
        rigs = sample_rigs(len(model.joints), 8)
        for row in time_model(model, rigs, [max(model.resolutions)], repeats):
            rows.append({"predictor": "onnxruntime-cuda", "bundle": "sample", **row})
    return rows


def part_train(device: str, dataset: Path | None, steps: int, folder: Path) -> dict[str, Any]:
    """`rigspace train` (train.loop.train) on a real dataset through its cache, 128x128."""
    if dataset is None:
        return {"skipped": "no --dataset given (a capture of samples/scenes/previs.usda)"}
    from rigspace.train.loop import train

    config, _ = sample_recipe()
    batch = 256
    config = replace(
        config,
        batch=batch,
        lr=config.lr * (batch / config.batch) ** 0.5,
        bf16=True,
        start_resolution=config.resolution,
        eval_every=10**9,
        checkpoint_every=10**9,
    )
    began = time.perf_counter()
    result = train(dataset, folder / "run", config, steps=steps, device=device)
    return {
        "wall_seconds": round(time.perf_counter() - began, 1),  # with the set-up and decoding
        "batch": batch,
        "lr": config.lr,
        "steps": result.step,
        "seconds": result.seconds,
        "images_per_s": result.images_per_second,
        "last_loss": result.last_loss,
    }


def part_frames(frames: int, folder: Path) -> list[dict[str, Any]]:
    """ms per 1920x1080 frame of the previs shot, 1 and 8 characters (Engine, auto), and the
    one-character frame again lit on the CPU (gl_lighting "never": what the shader saves)."""
    from rigspace.bench.scenes import crowd_scene
    from rigspace.runtime.engine import STAGES, Engine, EngineSettings

    rows = []
    for count, lighting in ((1, "hardware"), (8, "hardware"), (1, "never")):
        scene = PREVIS if count == 1 else crowd_scene(folder, count)
        engine = Engine(
            scene, EngineSettings(width=1920, height=1080, prim_samples=1, gl_lighting=lighting)
        )
        try:
            times = np.linspace(100.0, 1400.0, frames + 1)
            engine.render(float(times[0]))
            reports = [engine.render(float(t)).report.to_json() for t in times[1:]]
            runs_on = sorted({c.model.runner.description for c in engine.characters})
            runs_on.append(f"lighting: {reports[-1]['lighting_on']}")
        finally:
            engine.close()
        ms = {
            k: 1e3 * float(np.median([r["seconds"][k] for r in reports]))
            for k in (*STAGES, "total")
        }
        rows.append({"characters": count, "runs_on": runs_on, "ms": ms})
    return rows


def markdown(result: dict[str, Any]) -> str:
    lines = [f"GPU check on {result['machine'].get('gpu', 'no GPU')} ({result['machine']})", ""]
    parts = result["parts"]
    if "step" in parts:
        header = "| training step, 128x128 | batch | images/s | ms/step |"
        lines += [*_table(header, parts["step"], _step_row), ""]
    if "predictors" in parts:
        header = "| predictor | bundle | characters | ms per character |"
        lines += [*_table(header, parts["predictors"], _predictor_row), ""]
    if "train" in parts:
        t = parts["train"]
        lines.append(
            "rigspace train, real data through the cache: "
            + (
                f"skipped: {t['skipped']}"
                if "skipped" in t
                else f"{t['images_per_s']:.0f} images/s (batch {t['batch']}, bf16, {t['steps']} "
                f"steps; {t.get('wall_seconds', 0):.0f} s with the set-up and the items decoded "
                "into GPU memory)"
            )
        )
        lines.append("")
    if "frames" in parts:
        header = "| 1920x1080 frame | characters | total ms | per stage |"
        lines += _table(header, parts["frames"], _frame_row)
    return "\n".join(lines)


def _step_row(r: dict[str, Any]) -> str:
    precision = "bf16" if r["bf16"] else "fp32"
    return f"| {precision} | {r['batch']} | {r['images_per_s']:.0f} | {r['ms_per_step']:.2f} |"


def _predictor_row(r: dict[str, Any]) -> str:
    return (
        f"| {r['predictor']} ({r['runs_on']}) | {r['bundle']} | {r['batch']} | "
        f"{r['ms_per_character']:.3f} |"
    )


def _frame_row(r: dict[str, Any]) -> str:
    return (
        f"| {', '.join(r['runs_on'])} | {r['characters']} | {r['ms']['total']:.1f} | "
        + ", ".join(f"{k} {v:.1f}" for k, v in r["ms"].items() if k != "total")
        + " |"
    )


def _table(header: str, rows: Any, line: Callable[[dict[str, Any]], str]) -> list[str]:
    """A Markdown table of four columns: `header`, its rule, then a line per row (_rows)."""
    return [header, "|---|---|---|---|", *_rows(rows, line)]


def _rows(rows: Any, line: Callable[[dict[str, Any]], str]) -> list[str]:
    if isinstance(rows, dict) and "skipped" in rows:
        return [f"| skipped: {rows['skipped']} |||"]
    return [
        f"| {r['predictor']}: skipped: {r['skipped']} |||" if "skipped" in r else line(r)
        for r in rows
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.gpu_check",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", help="write every number as JSON here")
    parser.add_argument("--dataset", type=Path, help="a captured dataset, for the train part")
    parser.add_argument(
        "--device", default="cuda", help="cuda (default), cuda:N, or cpu (a dry run)"
    )
    parser.add_argument("--only", nargs="+", choices=("step", "predictors", "train", "frames"))
    parser.add_argument("--seconds", type=float, default=4.0, help="per step measurement")
    parser.add_argument("--batches", type=int, nargs="+", default=list(BATCHES))
    parser.add_argument("--resolutions", type=int, nargs="+", default=list(RESOLUTIONS))
    parser.add_argument("--repeats", type=int, default=50, help="per predictor timing")
    parser.add_argument("--train-steps", type=int, default=300)
    parser.add_argument("--frames", type=int, default=8)
    args = parser.parse_args(argv)
    parts = args.only or ["step", "predictors", "train", "frames"]
    result: dict[str, Any] = {
        "machine": machine(),
        "device": args.device,
        "parts": {},
        "seconds": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        jobs: dict[str, Callable[[], Any]] = {
            "step": lambda: part_step(args.device, args.seconds, tuple(args.batches)),
            "predictors": lambda: part_predictors(
                args.device, args.repeats, Path(tmp), tuple(args.resolutions)
            ),
            "train": lambda: part_train(args.device, args.dataset, args.train_steps, Path(tmp)),
            "frames": lambda: part_frames(args.frames, Path(tmp)),
        }
        for name in parts:
            start = time.monotonic()
            print(f"gpu_check: {name} ...", file=sys.stderr, flush=True)
            try:
                result["parts"][name] = jobs[name]()
            except ImportError as exc:  # usd-core or OpenImageIO missing: say what to install
                result["parts"][name] = {
                    "skipped": f"{exc} (install rigspace's dependencies: `pip install usd-core OpenImageIO`)"
                }
            result["seconds"][name] = round(time.monotonic() - start, 1)
            if args.out:
                write_atomic(args.out, json.dumps(result, indent=2, default=str) + "\n")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The bench's Markdown summary: one section per part that ran, from results.json's numbers."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def _f(value: Any, digits: int = 1) -> str:
    if value is None:
        return "-"
    try:
        return f"{float(value):.{digits}f}"
    except (TypeError, ValueError):
        return str(value)


def _ms(timing: dict[str, float] | None) -> str:
    if not timing:
        return "-"
    return f"{timing['median_ms']:.2f} ({timing['min_ms']:.2f}-{timing['max_ms']:.2f})"


Section = Callable[[Any], list[str]]


def _section(heading: str, text: str, *body: str) -> list[str]:
    """A part's section: its heading, a paragraph that says what was measured, its body (a
    table's lines)."""
    return [heading, "", text, "", *body]


def markdown(result: dict[str, Any], sections: list[tuple[str, Section]]) -> str:
    """The bench's README: the machine, then each measured part's section (`sections`: part
    name and its Markdown, in the order the parts run: bench.cli.BENCH_PARTS)."""
    m = result["machine"]
    lines = [
        "# rigspace bench results",
        "",
        f"`{result['command']}` ({result['mode']} mode), {result['date']}.",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, {m['memory']}, GPU: {m['gpu']}; "
        + ", ".join(f"{k} {v}" for k, v in m["versions"].items())
        + ". Timings: a warm-up, then the median of repeats (min-max). Seconds per part: "
        + ", ".join(f"{k} {v}" for k, v in result["seconds"].items())
        + ".",
    ]
    for part, section in sections:
        if part in result:
            lines += ["", *section(result[part])]
            run = result.get("parts", {}).get(part)
            if run and run.get("command", result["command"]) != result["command"]:
                lines += ["", f"(This part: `{run['command']}`, {run['date']}.)"]
            there = (run or {}).get("machine")
            if there and there != m:
                lines += [
                    "",
                    f"(Measured on another machine: {there['cpu']}, {there['cores']} cores.)",
                ]
    return "\n".join(lines) + "\n"


def _pareto(r: dict[str, Any]) -> list[str]:
    lines = _section(
        "## Run time against error",
        f"Truth: {r['truth']}; samples per split: {r['samples']}. Error of held-out views "
        "(held-out clip in brackets); time of one evaluation (batch 1) and of one full "
        f"runtime frame at {r['frame_size']}x{r['frame_size']}. ![pareto](pareto.png)",
        "| variant | albedo PSNR dB | SSIM | mask IoU | alpha IoU | depth % height | normal deg | ms per evaluation | ms per frame |",
        "|---|---|---|---|---|---|---|---|---|",
    )
    for row in r["rows"]:
        if "skipped" in row:
            lines.append(f"| {row['variant']} | skipped: {row['skipped']} ||||||||")
            continue
        views, clip = row.get("heldout-views", {}), row.get("heldout-clip", {})

        def cell(key: str, digits: int, views=views, clip=clip) -> str:
            text = _f(views.get(key), digits)
            return text + (f" ({_f(clip[key], digits)})" if key in clip else "")

        extra = ""
        if "footprint_bytes" in row:
            extra = f", keeps {row['footprint_bytes'] / 2**30:.2f} GiB"
        lines.append(
            f"| {row['variant']}{extra} | {cell('albedo_psnr', 2)} | {cell('albedo_ssim', 3)} | "
            f"{cell('mask_iou', 3)} | {cell('alpha_iou', 3)} | {cell('depth_mae_pct', 2)} | "
            f"{cell('normal_mean_deg', 1)} | "
            f"{_ms(row.get('evaluation'))} | {_ms(row.get('frame'))} |"
        )
    return lines


def _accuracy(r: dict[str, Any]) -> list[str]:
    from rigspace.bench.accuracy import format_table

    return _section(
        "## The runtime against the model",
        f"{len(r['samples'])} held-out samples; each map over the billboard's region, the "
        "model's own error (network at the ring camera) / the runtime's (Engine against "
        "Engine(reference=True)).",
        format_table(r),
    )


def _frames(rows: list[dict[str, Any]]) -> list[str]:
    from rigspace.bench.frame_stages import table

    return _section(
        "## Frame time by stage",
        "Previs scene (moving camera and props), prims drawn with 1 sample per pixel; ms.",
        table(rows),
    )


def _texture(rows: list[dict[str, Any]]) -> list[str]:
    from rigspace.bench.texture import table

    return _section(
        "## The character at the size it is seen (textures against the albedo branch)",
        "The previs shot against its skinned mesh (`--reference`): per frame the character "
        "region's albedo and beauty PSNR, its beauty FLIP (0 is identical; in brackets the "
        "ceiling, the mesh's region squeezed to the network's level and back) and its own "
        "coverage's IoU (medians over the frames), and milliseconds per frame (the texture "
        "sampler's own: `sampler ms`).",
        *table(rows),
    )


def _premise(r: dict[str, Any]) -> list[str]:
    from rigspace.bench.premise import crossover_sentence

    lines = _section(
        "## The premise: the mesh path against the network, by triangles",
        "The sample character subdivided (1 -> 4 triangles a step), in the previs shot at "
        "640x360, one frame of each path in turn; medians over 4 frames, ms. The mesh path: the "
        "skinned mesh drawn by the renderer as the character's layer (`--reference`), skinned as "
        "a user's CPU path skins it (sdk/skinning.py: numba LBS over the joints' skinning "
        "matrices, blend shapes, normals; equal to UsdSkel's skinning); its posing + skinning + "
        "raster is the frame's rig and network stages (the reference mode draws the mesh in the "
        "network's stage), its skinning the bench's own timing of the posed meshes. The network "
        "path as `rigspace render` runs by default (textures on): its network is the bench's "
        "timing of the bundle's graphs, its textures the sampler's. On a GPU the mesh path would "
        "skin in a vertex shader; that path is not built here (future work). "
        f"{crossover_sentence(r['rows'])} ![premise](premise.png)",
        "| triangles | mesh path ms | of which posing + skinning + raster | of which skinning "
        "| network path ms | of which network (graphs) | of which textures | mesh MiB "
        "| network MiB |",
        "|---|---|---|---|---|---|---|---|---|",
    )
    for row in r["rows"]:
        lines.append(
            f"| {row['triangles']:,} | {_f(row['mesh_ms'])} | "
            f"{_f(row.get('mesh_pose_raster_ms'))} | {_f(row.get('mesh_skinning_ms'))} | "
            f"{_f(row['network_ms'])} | {_f(row.get('network_graphs_ms'))} | "
            f"{_f(row.get('network_texture_ms'))} | {_f(row['mesh_mib'])} | "
            f"{_f(row['network_mib'])} |"
        )
    return lines


def _skips(r: dict[str, Any]) -> list[str]:
    lines = _section(
        "## What each skip costs",
        "Fraction of a full frame (still camera, character evaluated and lit) in the same "
        "run, 256x256. ![skips](skips.png)",
        "| case | " + " | ".join(f"{p} ms (fraction)" for p in r) + " | decision |",
        "|---|" + "---|" * len(r) + "---|",
    )
    first = next(iter(r.values()))
    for name in first["rows"]:
        cells = [
            f"{_ms(v['rows'][name])} ({v['rows'][name]['fraction_of_full']:.3f})"
            for v in r.values()
        ]
        row = first["rows"][name]
        what = "; ".join(row["decisions"]) + (f"; level {row['levels']}" if row["levels"] else "")
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {what} |")
    return lines


def _efficiency(r: dict[str, Any]) -> list[str]:
    peak = r["peak"]
    lines = _section(
        "## Close to the limit",
        f"Peak float32 matrix product ({peak['size']}^2): onnxruntime "
        f"{_f(peak['onnxruntime']['median_gflops'])} GFLOP/s, numpy "
        f"{_f(peak['numpy']['median_gflops'])} GFLOP/s. The network's FLOPs (trunk and both "
        "branches, convolutions and matrix products) per evaluation (batch 1) over its time, "
        "as a fraction of the float32 peak measured with the same threads in the same run. "
        "int8 rows count the same FLOPs: their fraction above 1 says int8 arithmetic has a "
        "higher peak than float32 (not measured here), not that the limit was passed.",
        "| threads | level | precision | MFLOP | ms | GFLOP/s | fraction of peak |",
        "|---|---|---|---|---|---|---|",
    )
    for row in r["rows"]:
        lines.append(
            f"| {row.get('threads') or 'all'} | {row['level']} | {row['precision']} | "
            f"{row['flops'] / 1e6:.0f} | {_f(row['ms_per_evaluation'], 2)} | "
            f"{_f(row['gflops'])} | {_f(row['fraction_of_peak'], 2)} |"
        )
    return lines


def _predictors(rows: list[dict[str, Any]]) -> list[str]:
    from rigspace.bench.predictors import table

    return table(rows)


def _data(r: dict[str, Any]) -> list[str]:
    from rigspace.bench.data import table

    return table(r)


def _capture(rows: list[dict[str, Any]]) -> list[str]:
    lines = ["## Capture throughput", "", "| renderer | resolution | samples/s |", "|---|---|---|"]
    for row in rows:
        if "skipped" in row:
            lines.append(f"| {row['renderer']} | - | skipped: {row['skipped']} |")
        else:
            lines.append(
                f"| {row['renderer']} | {row['resolution']} | {_f(row['samples_per_s'])} |"
            )
    return lines


def _training(r: dict[str, Any]) -> list[str]:
    lines = [
        "## Training throughput and stability",
        "",
        "| preset | resolution | batch | images/s | ms/step | every loss finite |",
        "|---|---|---|---|---|---|",
    ]
    for row in r["throughput"]:
        if "skipped" in row:
            lines.append(f"| {row['preset']} | skipped: {row['skipped']} |||||")
            continue
        lines.append(
            f"| {row['preset']} | {row['resolution']} | {row['batch']} | "
            f"{_f(row['images_per_s'])} | {_f(row['median_step_ms'])} | {row['finite']} |"
        )
    if "stability" in r:
        s = r["stability"]
        lines += [
            "",
            f"The `{s['preset']}` preset's own loop on the sample dataset, {s['steps']} steps "
            f"through levels {s['levels']}: every loss finite: {s['finite']} (first "
            f"{_f(s['first_loss'], 4)}, last {_f(s['last_loss'], 4)}, max {_f(s['max_loss'], 4)}).",
        ]
    return lines


def _memory(rows: list[dict[str, Any]]) -> list[str]:
    lines = _section(
        "## Memory",
        "Peak resident memory of a fresh process (MiB): after imports, after the Engine, after the frames.",
        "| characters | imports | engine | frames | ms per frame |",
        "|---|---|---|---|---|",
    )
    for row in rows:
        mib = row["peak_rss_mib"]
        lines.append(
            f"| {row['characters']} | {_f(mib['imports'], 0)} | {_f(mib['engine'], 0)} | "
            f"{_f(mib['frames'], 0)} | {_f(row['ms_per_frame'])} |"
        )
    return lines


def _stability(r: dict[str, Any]) -> list[str]:
    s = r["stress"]
    lines = _section(
        "## Numerical stability",
        f"{s['rigs']:,} adversarial rigs through the {s['precision']} network at level "
        f"{s['level']} ({', '.join(f'{k} {v}' for k, v in s['rigs_by_kind'].items())}; "
        "haar: uniform rotations, half_turn: 180-degree turns, near_gimbal: Euler middle "
        "angle within 1e-6 of 90 degrees, scaled: quaternions scaled by 1e-6 to 1e6, "
        f"mixed: any per joint) at {_f(s['rigs_per_second'])} rigs/s: outputs out of their "
        f"range or not finite: {sum(s['violations'].values()) if s['violations'] else 0} "
        f"({_compact(s['violations'])}); q against -q on {s['negated_pairs']} pairs: largest "
        f"output difference {max(s['negation_max_abs'].values()):.3g}.",
        "fp32 against int8 on the same rigs:",
        "",
        "| rigs, level | albedo PSNR dB | mask IoU | alpha IoU | depth mean abs | normal mean / p95 deg |",
        "|---|---|---|---|---|---|",
    )
    for name, d in r["drift"].items():
        lines.append(
            f"| {name} | {_f(d.get('albedo', {}).get('psnr_db'), 2)} | "
            f"{_f(d.get('mask', {}).get('iou_mean'), 3)} | {_f(d.get('alpha', {}).get('iou_mean'), 3)} | "
            f"{_f(d.get('depth', {}).get('mean_abs'), 3)} | "
            f"{_f(d.get('normal', {}).get('mean_deg'), 2)} / {_f(d.get('normal', {}).get('p95_deg'), 2)} |"
        )
    return lines


def _compact(value: Any) -> str:
    import json

    return json.dumps(value, default=str)[:1500]

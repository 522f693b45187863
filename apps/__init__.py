"""The apps layer: the `rigspace` subcommands and the `python -m` tools, above the library.

Each module is a thin front to library code (sdk, capture, train, runtime, bench): argument
parsing, console output, exit codes. Apps may import any library package; no library module
imports an app (tests/test_layering.py), so a library function an app and other library code
both need lives in the library.

Subcommands (entry-point group `rigspace.commands`, the front door is rigspace.sdk.cli):
`inspect`, `scaffold` (`rigspace init`), `capture`, `dataset`, `train` (train and eval; also
`python -m rigspace.apps.train`, the form torchrun runs), `render`, `live`, `view`, `bench`.

Tools (`python -m rigspace.apps.NAME`): `capsules`, `render_timing`, `capture_rates`,
`framing`, `ablation`, `curve`, `graph_rewrite`, `quantize`, `shadow_timing`, `live_send`,
`live_probe`, `live_fuzz`, `input_bench`, `scrub_bench`, `stability`, `memory`, `gpu_check`,
`regions_report` (docs/regions.md), `rerig_report` (docs/point_caches.md),
`recipe` (also `python3 apps/recipe.py`, on a machine without rigspace installed). What the
tools share (how a run ends, a user's error said in one line) is in `tools`.
"""

"""Numerical stability of a model bundle: adversarial rigs, its outputs' ranges, int8 drift.

    python -m rigspace.apps.stability                       # quick: 2,000 rigs, then drift
    python -m rigspace.apps.stability --long                # 100,000 rigs at level 16

What runs, and why, is rigspace.bench.stability's (the bench's stability part runs it too).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.bench.stability import (
    LONG_LEVEL,
    LONG_RIGS,
    PREVIS,
    SAMPLE_MODEL,
    animation_rigs,
    camera_frames,
    drift,
    haar,
    rigs,
    stress,
)
from rigspace.sdk.model import BundleModel

DESCRIPTION = (
    "Numerical stability: adversarial rigs through a model bundle, its outputs' ranges, int8 drift."
)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=DESCRIPTION)
    parser.add_argument("--model", type=Path, default=SAMPLE_MODEL)
    parser.add_argument("--precision", choices=("fp32", "int8"), default="fp32")
    parser.add_argument("--long", action="store_true", help=f"{LONG_RIGS} rigs at level 16")
    parser.add_argument("--rigs", type=int, default=2000)
    parser.add_argument("--level", type=int, default=LONG_LEVEL)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--drift-rigs", type=int, default=64, help="0: no drift")
    parser.add_argument("--drift-levels", type=int, nargs="+", default=[16, 128])
    parser.add_argument("--scene", type=Path, default=PREVIS, help="animation for drift rigs")
    parser.add_argument("--character", default="/World/Hero")
    args = parser.parse_args(argv)
    n, level = (LONG_RIGS, LONG_LEVEL) if args.long else (args.rigs, args.level)
    model = BundleModel(args.model, args.precision)
    result: dict[str, Any] = {"stress": stress(model, n, args.seed, level, args.batch)}
    if args.drift_rigs:
        fp32, int8 = BundleModel(args.model), BundleModel(args.model, "int8")
        rng = np.random.default_rng(args.seed)
        sets = {
            "haar": rigs(
                haar(rng, args.drift_rigs, len(fp32.joints)), camera_frames(rng, args.drift_rigs)
            ),
            "animation": animation_rigs(
                args.scene, args.character, fp32, args.drift_rigs, args.seed
            ),
        }
        result["drift"] = {
            f"{name}_{lv}": drift(fp32, int8, r, lv)
            for name, r in sets.items()
            for lv in args.drift_levels
        }
    print(json.dumps(result, indent=1), flush=True)


if __name__ == "__main__":
    main()

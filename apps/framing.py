"""How much of the capture frame the character fills: would a tighter framing add resolution?

    python -m rigspace.apps.framing DATASET [--samples 600]

The capture ring frames the character with one camera distance and focal length for every
pose, centred on the look-at joint (the runtime's billboard is placed the same way). A
tighter framing only adds effective resolution if the widest poses leave a margin: this
measures, on evenly spaced samples of every split, the side of the smallest square centred
on the frame that holds the character's coverage (mask >= 0.5), as a fraction of the frame.
Its maximum is the most a fixed framing could be tightened by without cropping a pose; its
median is what a per-pose framing (a scale per sample) could gain for a typical pose.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from rigspace.train.evaluate import DatasetTable

SPLITS = ("train", "heldout-views", "heldout-clips")


def centred_extent(mask: np.ndarray) -> float | None:
    """Side of the smallest frame-centred square holding the covered pixels, over the
    frame's side (None when nothing is covered)."""
    ys, xs = np.nonzero(mask >= 0.5)
    if len(ys) == 0:
        return None
    size = mask.shape[0]
    centre = (size - 1) / 2
    # Pixel centres lie half a pixel inside the square's edge.
    reach = max(np.abs(ys - centre).max(), np.abs(xs - centre).max()) + 0.5
    return float(2 * reach / size)


def measure(dataset: str, samples: int = 600) -> dict[str, float]:
    """Percentiles of the centred extent over `samples` evenly spaced samples of every split."""
    table = DatasetTable(dataset)
    counts = table.manifest.counts
    rows = np.concatenate([table.indices(s) for s in SPLITS if counts.get(s, 0)])
    picks = rows[np.unique(np.linspace(0, len(rows) - 1, min(samples, len(rows))).astype(int))]
    extents = [e for i in picks if (e := centred_extent(table.maps(int(i)).mask)) is not None]
    if not extents:
        raise SystemExit(f"rigspace framing: no sample of {dataset} covers a pixel.")
    values = np.array(extents)
    return {
        "samples": float(len(values)),
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "max": float(values.max()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.framing", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("dataset", help="a dataset folder written by `rigspace capture`")
    parser.add_argument("--samples", type=int, default=600, help="evenly spaced samples read")
    args = parser.parse_args(argv)
    m = measure(args.dataset, args.samples)
    print(
        f"{int(m['samples'])} samples: the frame-centred square holding the character is "
        f"{m['median']:.3f} of the frame at the median, {m['p95']:.3f} at the 95th percentile, "
        f"{m['max']:.3f} at most"
    )
    print(
        f"a fixed tighter framing gains at most {1 / m['max']:.2f}x linear resolution before it "
        f"crops the widest pose; a per-pose framing {1 / m['median']:.2f}x at the median"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

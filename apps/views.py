"""`python -m rigspace.apps.views BUNDLE DATASET`: add the training views of its look-at joint
(views.npy, rigspace.sdk.view_coverage) to a model bundle exported before them, from the
dataset it was trained on, so that its frames report views it never learned. `rigspace train`
writes them itself."""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

from rigspace.capture.dataset import read_manifest, training_views
from rigspace.sdk.bundle import MANIFEST_FILE, read_manifest_document, write_manifest_document
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.files import write_atomic
from rigspace.sdk.view_coverage import VIEWS_FILE, ViewCoverageError, views_bytes


def add_views(bundle: str | Path, dataset: str | Path) -> tuple[dict, str]:
    """Write views.npy into `bundle` from `dataset` and name it in the manifest (`views`,
    `files`), every other field as it was; returns the `views` section and its joint's name.
    A dataset other than the one the bundle records (its checksum) is refused before anything
    is written."""
    bundle, dataset = Path(bundle), Path(dataset)
    if not (bundle / MANIFEST_FILE).is_file():
        raise ViewCoverageError(
            f"{bundle} is not a model bundle (no manifest.json).", "pass the bundle's folder."
        )
    document = read_manifest_document(bundle)
    recorded = (document.get("dataset") or {}).get("checksum")
    checksum = read_manifest(dataset).checksum
    if recorded and checksum and recorded != checksum:
        raise ViewCoverageError(
            f"{bundle} was trained on a dataset with checksum {recorded[:12]}..., {dataset} "
            f"has {checksum[:12]}...",
            "pass the dataset the bundle was trained on (its manifest's dataset section).",
        )
    views = training_views(dataset, document["joints"])
    if views is None:
        raise ViewCoverageError(
            f"{dataset} has no training samples of a look-at joint.",
            "pass the dataset the bundle was trained on.",
        )
    coverage, every = views
    data = views_bytes(coverage)
    section = coverage.to_json(len(coverage.rotations), every)
    write_atomic(bundle / VIEWS_FILE, data)
    document["views"] = section
    document.setdefault("files", {})[VIEWS_FILE] = {
        "bytes": len(data),
        "sha256": hashlib.sha256(data).hexdigest(),
    }
    write_manifest_document(bundle, document)
    return section, document["joints"][coverage.joint]


def main(argv: list[str] | None = None) -> int:
    """`python -m rigspace.apps.views BUNDLE DATASET`: add a bundle's training views."""
    parser = argparse.ArgumentParser(prog="python -m rigspace.apps.views", description=__doc__)
    parser.add_argument("bundle", help="the model bundle folder (a body's or a region's)")
    parser.add_argument(
        "dataset", help="the dataset it was trained on (a region's: DS/regions/NAME)"
    )
    args = parser.parse_args(argv)
    try:
        section, joint = add_views(args.bundle, args.dataset)
    except RigspaceError as exc:
        print(f"rigspace views: error: {exc}", file=sys.stderr)
        return 1
    held = section.get("held_out_deg")
    print(
        f"{section['rows']} training views of {joint} (of {section['of']}) -> "
        f"{Path(args.bundle) / VIEWS_FILE}"
        + (
            f"; its held-out views lie {held['median']} deg outside them (median), "
            f"{held['p95']} (95th percentile)"
            if held
            else ""
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Capture on a local Ray cluster (2 CPUs): byte-identical to one process, also after a worker dies."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import pytest

from rigspace.apps import capture as cli
from rigspace.capture.ray_capture import DIE_ONCE, capture_on_ray
from tests.capture.conftest import CHARACTER, SCENE, SMALL

pytestmark = pytest.mark.slow  # starts a Ray cluster

ray = pytest.importorskip("ray", reason="capture on Ray needs the scale extra (ray)")


def tree(folder: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A local 2-CPU Ray cluster whose workers see DIE_ONCE (armed by creating its file)."""
    arm = tmp_path_factory.mktemp("ray") / "die-once"
    with pytest.MonkeyPatch.context() as env:
        env.setenv(DIE_ONCE, str(arm))  # workers inherit the driver's environment
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        try:
            yield arm
        finally:
            ray.shutdown()


def test_ray_capture_equals_one_process_even_when_a_worker_dies_mid_item(
    cluster, dataset, tmp_path
):
    cluster.write_text("armed")
    result = capture_on_ray(
        SCENE, CHARACTER, tmp_path / "ds", SMALL, progress=False, warn=lambda t: None
    )
    # One task really died mid-item (its record gone, a sample truncated) and was re-run.
    assert not cluster.exists() and Path(f"{cluster}.fired").is_file()
    assert result.complete and result.samples_done == dataset.manifest.counts["samples"]
    ours, theirs = tree(tmp_path / "ds"), tree(dataset.folder)
    assert sorted(ours) == sorted(theirs)
    assert [name for name in ours if ours[name] != theirs[name]] == []


def test_capture_cli_ray_flag_runs_on_the_cluster(cluster, dataset, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    out = tmp_path / "cli"
    args = parser.parse_args(
        [str(SCENE), "--out", str(out), "--views", "4", "--elevations", "0", "--resolution",
         "32", "--frames", "1:6", "--frames-per-item", "3", "--renderer", dataset.settings.renderer,
         "--ray"]
    )  # fmt: skip
    assert args.ray == "local"
    assert cli.run(args) == 0
    assert "dataset complete: 48 samples" in capsys.readouterr().out
    assert tree(out) == tree(dataset.folder)
    assert parser.parse_args([str(SCENE), "--out", "x", "--ray", "auto"]).ray == "auto"
    assert parser.parse_args([str(SCENE), "--out", "x"]).ray is None
    assert os.environ.get(DIE_ONCE)  # the cluster's workers were armed but no file: none died

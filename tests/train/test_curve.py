"""Quality against training time (python -m rigspace.apps.curve) on kept tiny checkpoints."""

from __future__ import annotations

import json
import shutil

import pytest

pytest.importorskip("torch", reason="the curve evaluates checkpoints with torch (train extra)")

from rigspace.apps import curve
from rigspace.train import loop
from rigspace.train.config import preset

TINY = preset("tiny")  # levels 16 and 32, 20 steps each; the 32 block has faded in at step 30


@pytest.fixture(scope="module")
def kept(tmp_path_factory, tiny_dataset):
    """A tiny run stopped at steps 20, 35 and 40, its checkpoint copied at each stop."""
    folder = tmp_path_factory.mktemp("curve")
    run, keep = folder / "run", folder / "kept"
    keep.mkdir()
    for k, steps in enumerate((20, 35, 40)):
        loop.train(tiny_dataset, run, TINY, steps=steps, resume=k > 0, progress=False)
        shutil.copyfile(run / loop.CHECKPOINT, keep / f"copy_{k}.pt")
    return run, keep


def test_points_are_the_trained_checkpoints_against_logged_minutes(kept, tiny_dataset, tmp_path):
    run, keep = kept
    out = tmp_path / "curve.png"
    assert (
        curve.main(
            [
                str(run),
                str(tiny_dataset),
                "--checkpoints",
                str(keep),
                "--limit",
                "8",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    points = json.loads(out.with_suffix(".json").read_text())
    # Step 20's network is mid-way: the 32x32 block had not faded in, so it is not a point.
    assert [p["step"] for p in points] == [35, 40]
    assert 0 < points[0]["minutes"] < points[1]["minutes"]
    views = points[1]["heldout-views"]
    assert 0 < views["albedo_psnr"] < 100 and 0 <= views["mask_iou"] <= 1
    assert "heldout-clips" not in points[1]  # the tiny dataset has no held-out clip
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_final_checkpoint_is_the_network_the_run_ends_with(kept, tiny_dataset):
    """The curve's last point evaluates the same weights as the run's own checkpoint."""
    run, keep = kept
    ours, _, step = loop.build_model(run, keep / "copy_2.pt")
    theirs, _, _ = loop.build_model(run)
    assert step == 40
    for (name, a), b in zip(ours.state_dict().items(), theirs.state_dict().values(), strict=True):
        assert a.equal(b), name


def test_an_old_log_takes_a_sampled_clock(kept, tiny_dataset, tmp_path):
    run, keep = kept
    old = tmp_path / "old"
    shutil.copytree(run, old)
    log = old / "log.jsonl"
    records = [json.loads(line) for line in log.read_text().splitlines()]
    log.write_text(
        "".join(json.dumps({k: v for k, v in r.items() if k != "seconds"}) + "\n" for r in records)
    )
    args = [
        str(old),
        str(tiny_dataset),
        "--checkpoints",
        str(keep),
        "--limit",
        "4",
        "--out",
        str(tmp_path / "c.png"),
    ]
    with pytest.raises(SystemExit, match="--clock"):
        curve.main(args)
    clock = tmp_path / "clock.txt"
    clock.write_text("1000 0\n1060 20\n1120 40\n")  # one minute per 20 steps
    assert curve.main([*args, "--clock", str(clock)]) == 0
    points = json.loads((tmp_path / "c.json").read_text())
    assert [round(p["minutes"], 3) for p in points] == [1.75, 2.0]


def test_extrapolation_follows_the_log_slope():
    def point(minutes, psnr):
        return {"minutes": minutes, "heldout-views": {"albedo_psnr": psnr}}

    rising = [point(10, 27.0), point(100, 29.0)]  # +2 dB per decade
    assert curve.extrapolate(rising, 31.0) == pytest.approx(1000.0)
    assert curve.extrapolate([point(10, 29.0), point(100, 28.0)], 31.0) is None

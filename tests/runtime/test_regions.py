"""Regions in the runtime (runtime/regions.py, the Engine, `rigspace render`): the merge of a
region's layer into its body's against a per-pixel reference, and a face region trained in
seconds drawn over the body when the camera is close, skipped with its reason when it adds
nothing, turned off by --no-regions, and left out with a warning when its bundle is damaged."""

from __future__ import annotations

import json
import math
import shutil
import sys
import threading

import cv2
import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from rigspace.runtime.billboard import Billboard
from rigspace.runtime.character import COVERAGE_EPSILON, Layer
from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.runtime.regions import (
    DEPTH_TOLERANCE,
    FEATHER_PX,
    SOLID,
    merge_region,
    merge_regions,
    region_skip,
    region_weight,
)
from rigspace.sdk.bundle import read_manifest_document, write_manifest_document
from rigspace.sdk.camera import Camera
from rigspace.sdk.cli import main
from tests.regions import ring_rows, trained_regions

MERGE_TOLERANCE = 1e-5
"""float32 blends against the float64 reference."""


def _layer(x0, y0, mask, depth, colour, normal=(0.0, 0.0, 1.0), uv=None, chart=None) -> Layer:
    mask = np.asarray(mask, np.float32)
    covered = mask > COVERAGE_EPSILON
    depth = np.where(covered, np.broadcast_to(np.float32(depth), mask.shape), np.inf)
    n = np.asarray(normal, np.float32) / np.linalg.norm(normal)
    return Layer(
        x0, y0,
        (mask[..., None] * np.asarray(colour, np.float32)).astype(np.float32),
        mask, depth.astype(np.float32),
        np.where(covered[..., None], n, 0.0).astype(np.float32),
        16, ("albedo", "geometry"), uv=uv, chart=chart,
    )  # fmt: skip


def _disc(h, w, cy, cx, radius) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w] + 0.5
    return np.clip(radius - np.hypot(y - cy, x - cx) + 0.5, 0.0, 1.0).astype(np.float32)


def reference_weight(body: Layer, region: Layer, feather: float, tolerance: float) -> np.ndarray:
    """region_weight pixel by pixel from its definition: a seam is any pixel the body covers at
    least SOLID where the region does not win; the distance to the nearest one by brute force."""

    def body_at(y, x):
        i, j = y - body.y0, x - body.x0
        if 0 <= i < body.mask.shape[0] and 0 <= j < body.mask.shape[1]:
            return float(body.mask[i, j]), float(body.depth[i, j])
        return 0.0, math.inf

    rh, rw = region.mask.shape
    wins = np.zeros((rh, rw), bool)
    for i in range(rh):
        for j in range(rw):
            _, depth = body_at(region.y0 + i, region.x0 + j)
            r, d = float(region.mask[i, j]), float(region.depth[i, j])
            wins[i, j] = r > COVERAGE_EPSILON and d <= depth * (1 + tolerance)
    x0, y0 = min(body.x0, region.x0), min(body.y0, region.y0)
    x1 = max(body.x0 + body.mask.shape[1], region.x0 + rw)
    y1 = max(body.y0 + body.mask.shape[0], region.y0 + rh)
    seams = []
    for y in range(y0, y1):
        for x in range(x0, x1):
            i, j = y - region.y0, x - region.x0
            mine = 0 <= i < rh and 0 <= j < rw and wins[i, j]
            if body_at(y, x)[0] >= SOLID and not mine:
                seams.append((y, x))
    seam = np.array(seams, float).reshape(-1, 2)
    out = np.zeros((rh, rw))
    for i in range(rh):
        for j in range(rw):
            if not wins[i, j]:
                continue
            f = 1.0
            if len(seam):
                d = np.hypot(seam[:, 0] - region.y0 - i, seam[:, 1] - region.x0 - j).min()
                t = min(d / feather, 1.0)
                f = t * t * (3 - 2 * t)
            b = min(max(body_at(region.y0 + i, region.x0 + j)[0], 0.0), 1.0)
            out[i, j] = 1 - (1 - f) * b
    return out


@pytest.fixture
def scene_layers():
    """A body covering a 20x24 rectangle's left 14 columns, at depth 3, and a face disc at
    depth 2.99 straddling the body's right edge (and its rectangle's)."""
    body_mask = np.zeros((20, 24), np.float32)
    body_mask[:, :14] = 1.0
    body_mask[:, 14] = 0.4  # the body's anti-aliased edge
    body = _layer(3, 2, body_mask, 3.0, (0.8, 0.2, 0.1), normal=(0.3, 0.0, 1.0))
    region = _layer(10, 5, _disc(12, 16, 6.0, 7.0, 5.0), 2.99, (0.1, 0.3, 0.9))
    return body, region


def test_the_weight_matches_its_definition_pixel_by_pixel(scene_layers):
    body, region = scene_layers
    weight, union = region_weight(body, region)
    assert union == (3, 2, 27, 22)
    expected = reference_weight(body, region, FEATHER_PX, DEPTH_TOLERANCE)
    assert np.abs(weight - expected).max() < MERGE_TOLERANCE
    # Feathered towards the seam inside the body, sharp against the background: beyond the
    # body's rectangle the region's weight is 1 wherever it covers.
    inside = (expected > 0) & (expected < 1)
    assert inside.any() and np.all(weight[:, 8:][region.mask[:, 8:] > 0] == 1.0)


def test_the_merge_puts_the_region_over_the_body_with_its_weight(scene_layers):
    body, region = scene_layers
    merged = merge_region(body, region)
    weight, _ = region_weight(body, region)
    assert (merged.x0, merged.y0, merged.mask.shape) == (3, 2, (20, 24))
    ry, rx = region.y0 - merged.y0, region.x0 - merged.x0
    inside = np.s_[ry : ry + 12, rx : rx + 16]
    w, r, b = weight, region.mask, body.mask[inside]
    k = w * r  # the region's alpha over the body
    expected_albedo = w[..., None] * region.albedo + (1 - k)[..., None] * body.albedo[inside]
    assert np.abs(merged.albedo[inside] - expected_albedo).max() < MERGE_TOLERANCE
    assert np.abs(merged.mask[inside] - (k + (1 - k) * b)).max() < MERGE_TOLERANCE
    # Under the region's soft edge the body stays solid: no hole where both are covered.
    both = (b == 1) & (r > 0)
    assert np.all(merged.mask[inside][both] > 1 - MERGE_TOLERANCE)
    # Normals: the blend by coverage, renormalised; depth: the region's where its share wins.
    blended = k[..., None] * region.normal + ((1 - k) * b)[..., None] * body.normal[inside]
    blended /= np.maximum(np.linalg.norm(blended, axis=-1, keepdims=True), 1e-12)
    drawn = weight > 0
    assert np.abs(merged.normal[inside][drawn] - blended[drawn]).max() < MERGE_TOLERANCE
    assert np.allclose(np.linalg.norm(merged.normal[merged.mask > 0], axis=-1), 1.0, atol=1e-5)
    wins = drawn & (k >= (1 - k) * b)
    assert np.all(merged.depth[inside][wins] == region.depth[wins])
    assert np.all(merged.depth[inside][~wins] == body.depth[inside][~wins])
    assert np.all(np.isfinite(merged.depth[merged.mask > 0]))  # every covered pixel is tested
    # Outside the region's winning pixels the body's values are kept to the bit.
    keep = np.ones(merged.mask.shape, bool)
    keep[inside] = ~drawn
    for a, c in ((merged.albedo, body.albedo), (merged.mask, body.mask)):
        assert np.array_equal(a[keep], c[keep])


def test_a_region_behind_the_body_or_empty_leaves_it_unchanged(scene_layers):
    body, region = scene_layers
    behind = _layer(region.x0, region.y0, region.mask, 3.0 * (1 + 2.5 * DEPTH_TOLERANCE),
                    (0.1, 0.3, 0.9))  # fmt: skip
    weight, _ = region_weight(body, behind)
    # Behind the body by more than the tolerance: only where the body is empty does it draw.
    ry, rx = behind.y0 - body.y0, behind.x0 - body.x0
    covered = body.mask[ry : ry + 12, rx : rx + 16]
    assert np.all(weight[covered >= SOLID] == 0) and np.all(weight[covered == 0][
        behind.mask[covered == 0] > COVERAGE_EPSILON] == 1)  # fmt: skip
    within = _layer(region.x0, region.y0, region.mask, 3.0 * (1 + 0.5 * DEPTH_TOLERANCE),
                    (0.1, 0.3, 0.9))  # fmt: skip
    assert np.all(region_weight(body, within)[0][region.mask > COVERAGE_EPSILON] > 0)
    empty = _layer(region.x0, region.y0, np.zeros_like(region.mask), 2.0, (1, 1, 1))
    assert merge_region(body, empty) is body  # the body unchanged, bit for bit


def test_uv_and_chart_follow_the_winner(scene_layers):
    body, region = scene_layers
    region.uv = np.full((*region.mask.shape, 2), 0.25, np.float32)
    region.chart = np.full(region.mask.shape, 3, np.int32)
    merged = merge_region(body, region)
    weight, _ = region_weight(body, region)
    ry, rx = region.y0 - merged.y0, region.x0 - merged.x0
    k, b = weight * region.mask, body.mask[ry : ry + 12, rx : rx + 16]
    wins = (weight > 0) & (k >= (1 - k) * b)
    chart = merged.chart[ry : ry + 12, rx : rx + 16]
    assert wins.any() and np.all(chart[wins] == 3) and np.all(chart[~wins] == 0)
    assert merged.uv is not None and np.all(merged.uv[ry : ry + 12, rx : rx + 16][wins] == 0.25)


def test_the_compiled_blend_equals_numpys(scene_layers):
    body, region = scene_layers
    rng = np.random.default_rng(7)
    region.uv = rng.random((*region.mask.shape, 2), np.float32)
    region.chart = rng.integers(1, 4, region.mask.shape).astype(np.int32)
    noisy = _layer(region.x0 - 4, region.y0 + 3, region.mask * rng.random(region.mask.shape),
                   2.9, (0.5, 0.5, 0.5), normal=(0.0, 0.6, 0.8))  # fmt: skip
    noisy.depth = np.where(noisy.mask > COVERAGE_EPSILON, rng.uniform(2.9, 3.1, noisy.mask.shape),
                           np.inf).astype(np.float32)  # fmt: skip
    for mine in (region, noisy):
        fast, slow = merge_region(body, mine), merge_region(body, mine, kernel=False)
        assert (fast.x0, fast.y0) == (slow.x0, slow.y0)
        for name in ("mask", "albedo", "depth", "normal", "uv"):
            a, b = getattr(fast, name), getattr(slow, name)
            assert (a is None) == (b is None), name
            if a is not None:
                finite = np.isfinite(b)
                assert np.array_equal(finite, np.isfinite(a)), name
                assert np.abs(a[finite] - b[finite]).max() < MERGE_TOLERANCE, name
        assert (fast.chart is None and slow.chart is None) or np.array_equal(fast.chart, slow.chart)


def test_regions_merged_at_once_equal_merging_them_one_by_one(scene_layers):
    """merge_regions copies the body once for all its regions: the result is the chain of
    merge_region (a later region depth-tested against the earlier ones, a hand before the
    face), over the rectangle holding them all; beyond the chain's, the fills."""
    body, face = scene_layers
    rng = np.random.default_rng(3)
    face.uv = rng.random((*face.mask.shape, 2), np.float32)
    face.chart = np.full(face.mask.shape, 2, np.int32)
    hand = _layer(face.x0 + 4, face.y0 - 2, _disc(10, 10, 5.0, 5.0, 4.0), 2.7, (0.9, 0.8, 0.1))
    behind = _layer(0, 0, _disc(8, 8, 4.0, 4.0, 3.5), 4.0, (0.2, 0.9, 0.2))  # beyond the body
    nothing = _layer(face.x0, face.y0, np.zeros_like(face.mask), 2.0, (1, 1, 1))
    regions = [face, nothing, hand, behind]
    at_once = merge_regions(body, regions)
    chain = body
    for r in regions:
        chain = merge_region(chain, r)
    assert (at_once.x0, at_once.y0) == (0, 0) == (chain.x0, chain.y0)
    h, w = chain.mask.shape
    for name in ("mask", "albedo", "depth", "normal", "uv", "chart"):
        a, c = getattr(at_once, name), getattr(chain, name)
        assert np.array_equal(a[:h, :w], c), name  # the same pass on the same values
    assert np.all(at_once.mask[h:] == 0) and np.all(at_once.mask[:, w:] == 0)
    assert merge_regions(body, [nothing]) is body and merge_regions(body, []) is body


def _billboard(size: float, visible: bool = True, reason: str = "") -> Billboard:
    corners = np.array([[0, 0], [size, 0], [size, size], [0, size]], float)
    return Billboard(np.zeros(3), np.eye(3), corners, 1.0, visible, reason)


def test_the_skip_rule_says_why():
    assert region_skip(_billboard(300), 128, _billboard(60), 64) == ""
    assert "not magnified" in region_skip(_billboard(100), 128, _billboard(30), 32)
    # 40 of the body's 128 network pixels lie across the face's 94 screen pixels: 32 adds none.
    assert "no finer than the body's 40" in region_skip(_billboard(300), 128, _billboard(94), 32)
    assert region_skip(_billboard(300), 128, _billboard(60, False, "outside the view"), 64) == (
        "outside the view"
    )


# -- the Engine and `rigspace render` on a face region trained in seconds --------------------


@pytest.fixture(scope="module")
def face(tmp_path_factory):
    return trained_regions(tmp_path_factory)


def _engine(scene, distance: float | None = None, **options) -> Engine:
    """An engine of the face scene at 96x72, its camera `distance` in front of the head."""
    engine = Engine(scene, EngineSettings(width=96, height=72, **options))
    if distance is not None:
        with Usd.EditContext(engine.stage, engine.stage.GetSessionLayer()):
            UsdGeom.XformCommonAPI(engine.camera_prim).SetTranslate(Gf.Vec3d(0, 1.0, distance))
    return engine


def _region_calls(engine: Engine) -> list[int]:
    """Counts the face network's calls from now on (in the returned list's one element)."""
    (part,) = engine.characters[0].regions
    calls = [0]
    predict = part.model.predict

    def counted(*args, **kwargs):
        calls[0] += 1
        return predict(*args, **kwargs)

    part.model.predict = counted  # type: ignore[method-assign]
    return calls


@pytest.mark.slow  # the face fixture trains two bundles (10-30 s)
def test_a_close_camera_draws_the_face_over_the_body(face):
    scene, _ = face
    with _engine(scene, 2.5) as engine, _engine(scene, 2.5, regions=False) as body_only:
        calls = _region_calls(engine)
        frame = engine.render(6.0)
        (hero,) = frame.report.characters
        (region,) = hero["regions"]
        assert hero["size_px"] > hero["level"]  # the body is magnified on screen
        assert region["name"] == "face" and region["decision"] == "evaluated"
        assert region["level"] == 16 and len(region["region"]) == 4 and calls == [1]
        assert frame.report.counts["regions evaluated"] == 1
        alone = body_only.render(6.0)
        (off,) = alone.report.characters[0]["regions"]
        assert off["decision"] == "skipped" and "turned off" in off["reason"]
        # The face changes the body's image inside its own square only.
        x, y, w, h = region["region"]
        changed = np.any(frame.beauty != alone.beauty, axis=-1)
        assert changed[y : y + h, x : x + w].any()
        changed[y : y + h, x : x + w] = False
        assert not changed.any()
        # The same time again: the frame is repeated, the face reused, no network call.
        again = engine.render(6.0)
        assert again.report.characters[0]["regions"][0]["decision"] == "reused"
        assert again.report.counts["regions reused"] == 1 and calls == [1]


@pytest.mark.slow  # the face fixture trains two bundles (10-30 s)
def test_the_face_s_network_runs_beside_the_body_s_and_draws_the_same(face, monkeypatch):
    """A frame's network calls run on NETWORK_WORKERS threads: the body's and the face's at
    once (each waits at a barrier for the other: on one thread the barrier would break), each
    holding its own model's lock; the frame is the one a single thread draws, bit for bit."""
    from rigspace.runtime.stages import characters

    scene, _ = face
    with _engine(scene, 2.5) as engine:
        meeting, calls = threading.Barrier(2, timeout=120), []
        evaluate = characters._evaluate

        def met(group, level, branches, camera, lock):
            calls.append((group[0].part.model, threading.current_thread().name, lock))
            if len(calls) <= 2:
                meeting.wait()  # both calls are running now
            assert lock.locked() is False  # a model's own calls are never this frame's two
            return evaluate(group, level, branches, camera, lock)

        monkeypatch.setattr(characters, "_evaluate", met)
        frame = engine.render(6.0)
    assert frame.report.characters[0]["regions"][0]["decision"] == "evaluated"
    (body, first, body_lock), (face_model, second, face_lock) = calls
    assert body is not face_model and first != second and body_lock is not face_lock
    monkeypatch.setattr(characters, "_evaluate", evaluate)
    monkeypatch.setattr(characters, "NETWORK_WORKERS", 1)
    with _engine(scene, 2.5) as engine:
        alone = engine.render(6.0)
    assert np.array_equal(frame.beauty, alone.beauty)


@pytest.mark.slow  # the face fixture trains two bundles (10-30 s)
def test_the_region_reads_at_a_ring_camera_the_rig_its_dataset_recorded(face):
    """The face's network input in the runtime (its billboard at its own joint, the joints'
    rotations in its virtual camera) equals the row its capture recorded at that camera."""
    scene, bundle = face
    table = np.load(bundle.parent / "ds" / "regions" / "face" / "params.npz")
    with _engine(scene, 2.5) as engine:
        hero = engine.characters[0]
        (part,) = hero.regions
        joints = len(part.order) * 6
        rows = range(0, len(table["time"]), max(1, len(table["time"]) // 5))
        for ours, recorded, billboard in ring_rows(part, hero.pose, table, rows):
            assert np.allclose(billboard.rotation, np.eye(3), atol=1e-6)  # it looks at the head
            assert np.abs(ours[0, :joints] - recorded).max() < 1e-4


@pytest.mark.slow  # the face fixture trains two bundles (10-30 s)
def test_a_head_rolled_about_the_line_of_sight_turns_the_face_s_billboard_not_its_input(face):
    """The face's ring kept the head's own up upright (`upright = "joint"`): the head turned
    30 degrees about the line of sight (with the joints below it) gives its network the same
    head row, and its billboard's corners turn 30 degrees about the head's projection; the
    body's (stage-upright) billboard does not turn."""
    scene, _ = face
    with _engine(scene, 2.5) as engine:
        hero = engine.characters[0]
        (part,) = hero.regions
        assert part.upright_axis is not None and hero.upright_axis is None
        camera = Camera.from_usd(engine.camera_prim, 6.0, 96, 72)
        world = hero.pose(6.0)
        head = part.look_at
        sight = world[head][:3, 3] - camera.camera_to_world[:3, 3]
        turn = np.eye(4)
        turn[:3, :3] = Gf.Matrix3d(Gf.Rotation(Gf.Vec3d(*sight), 30.0)).GetTranspose()
        # Turned about the head's own position: the head and below it, the neck not.
        about = np.eye(4)
        about[:3, 3] = world[head][:3, 3]
        rolled = world.copy()
        rolled[head] = about @ turn @ np.linalg.inv(about) @ world[head]
        before, after = part.place(world, camera), part.place(rolled, camera)
        row = slice(part.order.tolist().index(head) * 6, part.order.tolist().index(head) * 6 + 6)
        ours = part.parameters(world, before, camera)[0, row]
        theirs = part.parameters(rolled, after, camera)[0, row]
        assert np.abs(ours - theirs).max() < 1e-6
        edge = lambda b: b.corners[1] - b.corners[0]  # noqa: E731 (the top edge, in pixels)
        a, b = edge(before), edge(after)
        angle = math.degrees(math.atan2(a[0] * b[1] - a[1] * b[0], a @ b))
        assert abs(abs(angle) - 30.0) < 1.0
        body = hero.place(world, camera), hero.place(rolled, camera)
        np.testing.assert_allclose(body[0].corners, body[1].corners)


@pytest.mark.slow  # the face fixture trains two bundles (10-30 s)
def test_far_or_without_its_body_the_face_is_skipped_and_runs_nothing(face):
    scene, _ = face
    with _engine(scene, 60.0) as engine:
        calls = _region_calls(engine)
        far = engine.render(6.0)
        hero = far.report.characters[0]
        assert hero["decision"] == "evaluated" and hero["size_px"] <= hero["level"]
        (region,) = hero["regions"]
        assert region["decision"] == "skipped" and "not magnified" in region["reason"]
        assert far.report.counts["regions skipped"] == 1
        with Usd.EditContext(engine.stage, engine.stage.GetSessionLayer()):
            UsdGeom.XformCommonAPI(engine.camera_prim).SetRotate(Gf.Vec3f(0, 180, 0))
        behind = engine.render(7.0)
        hero = behind.report.characters[0]
        assert hero["decision"] == "skipped" and hero["reason"] == "behind the camera"
        assert hero["regions"][0]["reason"] == "its character is not drawn this frame"
        assert calls == [0]


@pytest.mark.slow  # the face fixture trains two bundles (10-30 s)
def test_render_draws_the_face_and_no_regions_gives_the_body_alone(face, tmp_path):
    scene, bundle = face
    # The body alone: the same bundle with no regions in its manifest.
    alone = tmp_path / "alone"
    shutil.copytree(bundle, alone, ignore=shutil.ignore_patterns("regions", "training"))
    document = read_manifest_document(alone)
    del document["regions"]
    write_manifest_document(alone, document)
    common = ["--frames", "6:6", "--resolution", "96x72", "--camera", "/World/Camera"]
    with_face, without, body = tmp_path / "face", tmp_path / "without", tmp_path / "body"
    assert main(["render", str(scene), "--out", str(with_face), *common, "--reference"]) == 0
    assert main(["render", str(scene), "--out", str(without), *common, "--no-regions"]) == 0
    assert main(["render", str(scene), "--out", str(body), *common, "--model", str(alone)]) == 0
    png = "frame_000006.0.png"
    image = {k: cv2.imread(str(k / png)) for k in (with_face, without, body)}
    assert np.array_equal(image[without], image[body])
    assert not np.array_equal(image[with_face], image[body])
    report = json.loads((with_face / "report.json").read_text())["frames"][0]
    (region,) = report["characters"][0]["regions"]
    assert region["decision"] == "evaluated" and report["counts"]["regions evaluated"] == 1
    # --reference measures the face over its own square too.
    (numbers,) = report["reference"][0]["regions"]
    assert numbers["name"] == "face" and numbers["region"] == region["region"]
    assert math.isfinite(numbers["psnr"]) and 0 <= numbers["flip"] <= 1
    off = json.loads((without / "report.json").read_text())["frames"][0]
    assert off["characters"][0]["regions"][0]["decision"] == "skipped"


def _no_manifest(folder):
    (folder / "manifest.json").unlink()
    return "no manifest.json"


def _no_graph(folder):
    trunk = read_manifest_document(folder)["trunk"]["graphs"]["trunk"]
    (folder / trunk).unlink()
    return f"{trunk} is missing"


def _strange_joint(folder):
    document = read_manifest_document(folder)
    document["joints"] = [*document["joints"][:-1], "tail"]
    write_manifest_document(folder, document)
    return "joints the skeleton lacks: tail"


@pytest.mark.slow
@pytest.mark.parametrize("damage", [_no_manifest, _no_graph, _strange_joint])
def test_a_damaged_region_bundle_warns_and_the_body_draws(face, tmp_path, capsys, damage):
    scene, bundle = face
    copy = tmp_path / "model"
    shutil.copytree(bundle, copy, ignore=shutil.ignore_patterns("training"))
    said = damage(copy / "regions" / "face")
    with _engine(scene, models={"": str(copy)}) as engine, _engine(scene, regions=False) as alone:
        warning = capsys.readouterr().err
        assert "region face is not drawn, the body draws without it" in warning
        assert said in warning and str(copy / "regions" / "face") in warning
        assert "Fix:" in warning and "--no-regions" in warning
        frame = engine.render(6.0)
        hero = frame.report.characters[0]
        assert hero["decision"] == "evaluated"
        assert hero["regions"][0]["decision"] == "skipped"
        assert said in hero["regions"][0]["reason"]
        assert np.array_equal(frame.beauty, alone.render(6.0).beauty)


# -- python -m rigspace.apps.regions_report: the parts over their own pixels, draw by draw ----


@pytest.mark.slow  # the face fixture trains two bundles (10-30 s)
def test_the_regions_report_measures_each_part_with_and_without_its_region(face, tmp_path):
    from rigspace.apps import regions_report

    scene, _ = face
    out = tmp_path / "report"
    common = ["--frames", "6:7", "--step", "1", "--width", "96", "--height", "72"]
    assert regions_report.main([str(scene), "--out", str(out), *common,
                                "--part", "neck=neck"]) == 0  # fmt: skip
    result = json.loads((out / "regions_report.json").read_text())
    assert set(result["parts"]) == {"face", "neck"} and result["frames"] == [6.0, 7.0]
    face_rows = result["parts"]["face"]
    assert set(face_rows) == {"regions", "body"}
    for row in face_rows.values():
        assert row["frames"] == 2 and row["pixels"] > 2 * regions_report.MIN_PIXELS
        assert 0 <= row["flip"] <= 1 and 0 <= row["mask_iou"] <= 1
    # The face network draws the face's pixels: its numbers are not the body's.
    assert face_rows["regions"]["psnr"] != face_rows["body"]["psnr"]
    # The part image: a header, then per frame the reference and each draw side by side.
    sheet = cv2.imread(str(out / "part_face.png"))
    side = regions_report.CROP_PX
    assert sheet.shape[1] == 3 * side and (sheet.shape[0] - 24) % side == 0
    assert "| regions |" in (out / "regions_report.md").read_text()
    # A row per frame and draw, which add up to the totals; the plot of them, one line a draw.
    rows = result["per_frame"]["face"]
    assert [r["t"] for r in rows["regions"]] == [6.0, 7.0]
    for label, frames in rows.items():
        assert sum(r["pixels"] for r in frames) == face_rows[label]["pixels"]
        assert np.median([r["psnr"] for r in frames]) == pytest.approx(
            face_rows[label]["median_frame_psnr"], abs=0.01
        )
    assert "Where the draws differ most" in (out / "regions_report.md").read_text()
    plot = cv2.imread(str(out / "frames_face.png"))
    assert plot is not None and plot.shape[1] > 400


@pytest.mark.slow  # the face fixture trains two bundles (10-30 s)
def test_the_regions_report_names_a_bad_part_and_writes_nothing(face, tmp_path, capsys):
    from rigspace.apps import regions_report

    scene, _ = face
    out = tmp_path / "report"
    argv = [str(scene), "--out", str(out), "--frames", "6:6", "--part", "tail=tail_01"]
    assert regions_report.main(argv) == 1
    assert "tail_01" in capsys.readouterr().err and not out.exists()


@pytest.mark.slow  # captures and trains a body and a region with texture heads (10-40 s)
def test_a_region_with_a_texture_head_samples_the_characters_textures(tmp_path):
    """The film character's regions train with the small preset's texture head: a region's
    bundle then has texture charts of its own, and its layer samples the character's textures."""
    from tests.capture.test_regions import _with_region
    from tests.materials import CHARACTER, write_material_character

    scene = write_material_character(tmp_path / "scene")
    _with_region(scene, name="top", joint="root/mid/top", resolution=32, size=1.0)
    dataset, bundle = tmp_path / "ds", tmp_path / "model"
    capture = ["capture", str(scene), "--out", str(dataset), "--views", "2", "--every", "6",
               "--resolution", "32", "--workers", "1", "--regions"]  # fmt: skip
    assert main(capture) == 0
    train = ["train", str(dataset), "--out", str(bundle), "--preset", "tiny", "--steps", "3",
             "--no-int8", "--texture"]  # fmt: skip
    assert main(train) == 0
    region = json.loads((bundle / "regions" / "top" / "manifest.json").read_text())
    assert (
        region["texture"]["charts"] > 0 and (bundle / "regions" / "top" / "charts.json").is_file()
    )
    stage = Usd.Stage.Open(str(scene))
    stage.GetPrimAtPath(CHARACTER).GetAttribute("rigspace:model").Set(str(bundle))
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/Asset")).CreatePurposeAttr("guide")
    stage.GetRootLayer().Save()
    with _engine(scene, 2.5) as engine:
        (part,) = engine.characters[0].regions
        assert part.textures is not None, part.no_texture
        frame = engine.render(6.0)
    (entry,) = frame.report.characters[0]["regions"]
    assert entry["decision"] == "evaluated", entry
    assert entry["colour"].startswith("its textures on"), entry["colour"]


def test_the_regions_report_lists_the_frames_where_its_draws_differ_most():
    from rigspace.apps.regions_report import _spread

    def row(t, psnr):
        return {"t": t, "pixels": 100, "psnr": psnr, "flip": 0.3, "mask_iou": 0.9}

    rows = {
        "a": [row(0.0, 12.0), row(10.0, 14.0), row(20.0, 13.0)],
        "b": [row(0.0, 12.5), row(10.0, 9.0), row(20.0, 13.0)],
    }
    lines = _spread(rows)
    table = [line for line in lines if line.startswith("| ") and line[2].isdigit()]
    assert [line.split(" | ")[0] for line in table] == ["| 10", "| 0", "| 20"]
    assert "14.00 / 0.300 | 9.00 / 0.300" in table[0]
    # One draw, or no frame every draw measured: nothing to compare.
    assert _spread({"a": rows["a"]}) == []
    assert _spread({"a": rows["a"], "b": []}) == []


def test_the_regions_report_says_why_it_draws_no_frame_plot(tmp_path, monkeypatch):
    from rigspace.apps.regions_report import plot_frames

    row = {"t": 0.0, "pixels": 100, "psnr": 12.0, "flip": 0.3, "mask_iou": 0.9}
    path = tmp_path / "frames_face.png"
    assert plot_frames({"a": [row]}, path, "face") == "one draw: nothing to compare"
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # not installed
    assert "matplotlib is not installed" in plot_frames({"a": [row], "b": [row]}, path, "face")
    assert not path.exists()

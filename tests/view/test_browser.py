"""The page in a real headless Chromium (Debian's, driven by playwright) on real stages.

RIGSPACE_VIEW_SCREENSHOTS=DIR also writes a screenshot of each panel there (docs/images).
"""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path

import pytest

from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.send import humanoid_clip, send_vmc
from tests.conftest import REPO, free_port
from tests.view.conftest import BROKEN, LIVE, served

pytestmark = pytest.mark.slow  # a real Chromium: the quick subset leaves it out

SHOTS = os.environ.get("RIGSPACE_VIEW_SCREENSHOTS")
WINDOW = {"width": 1600, "height": 950}
PIXELS = """() => {
  const c = document.getElementById('viewport');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  const out = [];
  for (let i = 0; i < d.length; i += 4 * 97) out.push(d[i], d[i + 1], d[i + 2]);
  return out;
}"""


def shot(page, selector: str, name: str) -> None:
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        target = page if selector == "page" else page.locator(selector)
        target.screenshot(path=str(Path(SHOTS) / f"view_{name}.png"))


def open_page(browser, url: str):
    page = browser.new_page(viewport=WINDOW)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(url)
    page.wait_for_function("window.rigspaceView && window.rigspaceView.summary", timeout=30_000)
    return page, errors


def wait_frame(page, condition: str, timeout: float = 60_000) -> None:
    page.wait_for_function(
        f"(() => {{ const h = window.rigspaceView.viewport.last; return h && ({condition}); }})()",
        timeout=timeout,
    )


def open_hero_sliders(browser, url: str, sliders: str):
    """open_page, then /World/Hero picked in the tree once the full-quality frame is drawn,
    until the inspector shows its `sliders` (a selector): the page and its errors."""
    page, errors = open_page(browser, url)
    wait_frame(page, "h.quality === 'full'")
    page.click('.node[data-path="/World/Hero"]')
    page.locator(sliders).wait_for()
    return page, errors


def difference(a: list[int], b: list[int]) -> float:
    return sum(abs(x - y) for x, y in zip(a, b, strict=True)) / len(a)


def test_previs_select_scrub_and_switch_maps(browser, previs_served):
    _, url = previs_served
    page, errors = open_page(browser, url)
    wait_frame(page, "h.time === 0 && h.quality === 'full'")
    # Select the character in the tree and read its properties at the current time.
    page.click('.node[data-path="/World/Hero"]')
    row = page.locator('#props tr[data-prop="rigspace:model"]')
    row.wait_for()
    assert "authored" in row.inner_text() and "sample" in row.inner_text()
    assert page.locator("#props-path").inner_text() == "/World/Hero"
    assert page.locator("#bundle-metrics tr").count() >= 2  # the bundle's evaluation rows
    assert "previs.usda" in page.locator("#arcs").inner_text()
    before = page.evaluate(PIXELS)
    # Scrub: the viewport's pixels change, a paint is measured for the new time.
    page.evaluate(
        "t => { const s = document.getElementById('scrub'); s.value = t;"
        " s.dispatchEvent(new Event('input')); }",
        300,
    )
    wait_frame(page, "h.time === 300 && h.quality === 'full'")
    after = page.evaluate(PIXELS)
    assert difference(before, after) > 2.0
    paints = page.evaluate("window.rigspaceView.paints.filter(p => p.time === 300)")
    assert paints and paints[0]["ms"] > 0
    decision = page.locator('#decisions tr[data-character="/World/Hero"]').inner_text()
    assert "evaluated" in decision or "reused" in decision
    shot(page, "page", "overview")
    for panel in ("tree", "props", "viewport", "timeline"):
        shot(page, f"#{panel}-panel", panel)
    page.locator("#bundle-metrics").scroll_into_view_if_needed()
    shot(page, "#props-panel", "bundle")
    # The skinned asset is referenced in: the composition panel names both layers.
    page.click('.node[data-path="/World/Hero/Asset"]')
    page.wait_for_function(
        "() => document.querySelector('#arcs') && "
        "document.querySelector('#arcs').textContent.includes('Reference')"
    )
    assert "sample_character.usda" in page.locator("#arcs").inner_text()
    shot(page, "#comp-panel", "comp")
    # Switch the map: normals look nothing like the beauty.
    page.click('#maps button[data-map="normal"]')
    wait_frame(page, "h.map === 'normal' && h.time === 300")
    normal = page.evaluate(PIXELS)
    assert difference(after, normal) > 10.0
    shot(page, "#viewport-panel", "viewport_normal")
    page.click('#maps button[data-map="depth"]')
    wait_frame(page, "h.map === 'depth'")
    assert difference(normal, page.evaluate(PIXELS)) > 10.0
    # Play advances in real time at the stage's rate; pause refines the frame on screen.
    page.click("#play")
    page.wait_for_function("window.rigspaceView.state.time > 330", timeout=60_000)
    page.click("#play")
    stopped = page.evaluate("window.rigspaceView.state.time")
    wait_frame(page, f"h.time === {stopped} && h.quality === 'full'")
    shot(page, "#decisions-panel", "decisions")
    shot(page, "#graph-panel", "graph")
    assert not errors, errors
    page.close()


def test_broken_fixture_links_its_validation_error_to_its_prim(browser):
    with served(BROKEN) as (viewer, url):
        assert viewer.frames.error  # the Engine refuses the scene: no frames, panels work
        page, errors = open_page(browser, url)
        finding = page.locator('.finding[data-code="NotASkeleton"]')
        finding.wait_for()
        assert finding.get_attribute("data-prim") == "/World/Hero"
        assert "rigspace:skeleton targets /World/Camera" in finding.inner_text()
        shot(page, "#findings-panel", "findings")
        finding.locator("a.prim").click()
        page.locator('.node.sel[data-path="/World/Hero"]').wait_for()
        page.locator('#props tr[data-prop="rigspace:skeleton"]').wait_for()
        assert page.locator("#props-path").inner_text() == "/World/Hero"
        assert page.locator('.node[data-path="/World/Hero"] .dot-error').count() == 1
        assert page.locator("#viewport-error").is_visible()
        assert "No frames" in page.locator("#viewport-error").inner_text()
        assert "stop render" in page.locator("#viewport-error").inner_text()
        shot(page, "page", "broken")
        assert not errors, errors
        page.close()


def test_an_edit_on_disk_reloads_and_a_syntax_error_becomes_a_finding(browser, tmp_path):
    scene = tmp_path / "scene.usda"
    shutil.copy(BROKEN, scene)
    with served(scene) as (_, url):
        page, errors = open_page(browser, url)
        page.locator('.node[data-path="/World/Camera"]').wait_for()
        text = scene.read_text()
        scene.write_text(text.replace('def Camera "Camera"', 'def Camera "Witness"'))
        os.utime(scene, ns=(1, 1))
        page.locator('.node[data-path="/World/Witness"]').wait_for(timeout=20_000)
        scene.write_text(text + '\ndef Xform "Oops" {{{\n')
        os.utime(scene, ns=(2, 2))
        page.locator('.finding[data-code="LayerParseError"]').wait_for(timeout=20_000)
        assert page.locator('.node[data-path="/World/Witness"]').count() == 1  # kept
        assert not errors, errors
        page.close()


def test_live_binding_counters_rise_while_a_sender_streams(browser):
    skeleton, motion, frame_time = read_bvh(REPO / "samples" / "motion" / "cmu_131_01.bvh")
    rotations, roots = skeleton.pose(motion)
    clip = humanoid_clip(skeleton, rotations[:120], roots[:120], frame_time)
    source = f"vmc://127.0.0.1:{free_port()}"
    stop = threading.Event()
    with served(LIVE, sources={"suit": source}) as (viewer, url):
        assert viewer.frames.live and viewer.frames.live_error is None
        # Before the sender starts the binding waits: the pose holds, the camera is still,
        # so the Engine hands back its last image and the server its last JPEG.
        first, data = viewer.worker.submit(
            viewer.frames.frame, 10.0, "beauty", "neural", "full"
        ).result()
        again, same = viewer.worker.submit(
            viewer.frames.frame, 10.0, "beauty", "neural", "full"
        ).result()
        assert not first.get("reused") and again.get("reused") and same == data
        assert again["report"]["composite_reused"]
        sender = threading.Thread(target=send_vmc, args=(source, clip, 1.0, True, stop))
        sender.start()
        try:
            page, errors = open_page(browser, url)
            cell = page.locator('#live-table tr[data-binding="suit"] [data-counter="packets"]')
            page.wait_for_function(
                "() => { const c = document.querySelector("
                '\'#live-table tr[data-binding="suit"] [data-counter="samples"]\');'
                " return c && Number(c.textContent) > 0; }",
                timeout=30_000,
            )
            first = int(cell.inner_text())
            time.sleep(1.5)
            page.wait_for_function(
                f"() => Number(document.querySelector("
                f'\'#live-table tr[data-binding="suit"] [data-counter="packets"]\')'
                f".textContent) > {first}",
                timeout=15_000,
            )
            status = page.locator('#live-table tr[data-binding="suit"] .st').inner_text()
            assert status == "connected"
            shot(page, "#live-panel", "live")
            assert not errors, errors
            page.close()
        finally:
            stop.set()
            sender.join()


@pytest.fixture(autouse=True)
def _needs_browser(browser):
    """Every test here drives the session's Chromium (skipped where it is missing)."""


@pytest.mark.parametrize("width", [1280, 1400, 1600])
def test_every_column_fits_the_window(browser, previs_served, width):
    """The three columns shrink to the window: at 1400 px the right one was clipped (issue 22)."""
    _, url = previs_served
    page = browser.new_page(viewport={"width": width, "height": 900})
    page.goto(url)
    page.wait_for_function("window.rigspaceView && window.rigspaceView.summary", timeout=30_000)
    for column in ("#left", "#center", "#right"):
        box = page.locator(column).bounding_box()
        assert box is not None and box["width"] > 150, column
        assert box["x"] >= 0 and box["x"] + box["width"] <= width + 0.5, (column, box)
    page.close()


def test_blend_shape_sliders_override_the_animations_weights(browser, tmp_path_factory):
    """A character whose model reads blend shapes gets a slider per shape in the inspector:
    dragging jawOpen shut (the animation has it fully open at the first frame) re-renders the
    face with it (the server's engines hold the override), reset gives the animation back."""
    from tests.blendshapes import trained_face

    scene, _ = trained_face(tmp_path_factory)
    with served(scene) as (viewer, url):
        page, errors = open_hero_sliders(browser, url, "#blend-sliders")
        names = page.locator("#blend-sliders input").evaluate_all(
            "nodes => nodes.map(n => n.dataset.shape)"
        )
        assert names == ["smile", "blink", "jawOpen", "frown", "brow"]
        keep = (
            "() => { const c = document.getElementById('viewport');"
            " window.kept = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; }"
        )
        changed = (
            "() => { const c = document.getElementById('viewport');"
            " const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
            " let n = 0; for (let i = 0; i < d.length; i += 4)"
            " if (Math.abs(d[i] - window.kept[i]) + Math.abs(d[i + 1] - window.kept[i + 1]) > 24) n++;"
            " return n; }"
        )
        page.evaluate(keep)
        seen = page.evaluate("window.rigspaceView.frames")
        page.evaluate(
            "() => { const s = document.querySelector('input[data-shape=\"jawOpen\"]');"
            " s.value = 0; s.dispatchEvent(new Event('input')); }"
        )
        wait_frame(page, f"window.rigspaceView.frames > {seen} && h.quality === 'full'")
        assert viewer.frames.engines.full.weight_overrides == {"/World/Hero": {"jawOpen": 0.0}}
        assert page.evaluate(changed) > 20  # the jaw's pixels moved
        page.locator("#blend-sliders").scroll_into_view_if_needed()
        shot(page, "#props-panel", "blend_sliders")
        seen = page.evaluate("window.rigspaceView.frames")
        page.click("#weights-reset")
        wait_frame(page, f"window.rigspaceView.frames > {seen} && h.quality === 'full'")
        assert not page.evaluate("window.rigspaceView.state.weights['/World/Hero']")
        assert page.evaluate(changed) < 5  # the animation's face again
        assert viewer.frames.engines.full.weight_overrides == {}
        assert not errors, errors
        page.close()


def test_a_rigs_controls_get_sliders_over_their_ranges(browser, tmp_path_factory):
    """A character whose model reads a named control (docs/point_caches.md) gets a slider for
    it over the control's own range, and a slider moved travels in the frame request (the
    engine takes it as an override: tests/train/test_point_caches.py)."""
    from tests.point_caches import CONTROL, trained_arm

    scene, _ = trained_arm(tmp_path_factory)
    with served(scene) as (_, url):
        page, errors = open_hero_sliders(browser, url, "#control-sliders")
        found = page.locator("#control-sliders input").evaluate_all(
            "nodes => nodes.map(n => [n.dataset.control, n.min, n.max])"
        )
        assert found == [[CONTROL, "0", "1"]]
        page.evaluate(
            "() => { const s = document.querySelector('input[data-control=\"bulge\"]');"
            " s.value = 0.5; s.dispatchEvent(new Event('input')); }"
        )
        assert page.evaluate("window.rigspaceView.state.controls['/World/Hero']") == {CONTROL: 0.5}
        page.click("#controls-reset")
        assert not page.evaluate("window.rigspaceView.state.controls['/World/Hero']")
        assert not errors, errors
        page.close()


def test_a_characters_regions_show_in_the_overlay_and_the_decisions(browser, tmp_path_factory):
    """A character whose bundle has a face region: the face's square is drawn on the overlay
    (its own toggle, apart from the characters' overlay) and its decision has a row of its own
    in the decisions table."""
    from tests.regions import trained_regions

    scene, _ = trained_regions(tmp_path_factory)
    overlay = (
        "() => { const c = document.getElementById('overlay');"
        " const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        " let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n; }"
    )
    with served(scene) as (_, url):
        page, errors = open_page(browser, url)
        wait_frame(page, "h.quality === 'full'")
        row = page.locator('#decisions tr[data-region="/World/Hero#face"]')
        row.wait_for()
        text = row.inner_text()  # the engine drew the first frame when it opened: reused
        assert "region face" in text and ("evaluated" in text or "reused" in text), text
        assert "16/16" in text
        page.click("#overlay-toggle")  # the characters' overlay off: the region's square stays
        with_regions = page.evaluate(overlay)
        shot(page, "#viewport-panel", "regions")
        page.click("#regions-toggle")
        assert with_regions > 100 and page.evaluate(overlay) == 0
        assert not errors, errors
        page.close()

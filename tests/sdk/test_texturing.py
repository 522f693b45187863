"""The runtime's texture sampler: mip chains, the numba kernel against its numpy reference,
exact reads where the texture is magnified, chart borders, fallbacks and edge sharpening."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.sdk.geometry import Albedo, MeshSource
from rigspace.sdk.render.embree import sample_bilinear
from rigspace.sdk.texturing import (
    ChartTextures,
    TextureMismatch,
    display_colour,
    magnification,
    mip_chain,
    region_warper,
    sample_textures,
    sharpen_coverage,
)

KERNEL_TOLERANCE = 1e-5
"""Kernel (float64 scalar) against reference (float32 texture reads): rounding only."""


def _source(texture, wrap=("repeat", "repeat"), name="Body", udim=False) -> MeshSource:
    triangles = np.array([[0, 1, 2]], np.int32)
    uv = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]], np.float32)
    albedo = Albedo(np.zeros(3, np.float32), texture, "st", wrap)
    if udim:  # an atlas of two tiles side by side, 1001 and 1002
        albedo.uv_scale, albedo.udim, albedo.wrap = (0.5, 1.0), True, ("clamp", "clamp")
    return MeshSource(name, np.zeros((3, 3), np.float32), triangles, uv, albedo)


def _table(boxes, mesh="Body", fingerprint=None) -> dict:
    charts = [
        {"index": k + 1, "mesh": mesh, "tile": 1001, "uv_min": lo, "uv_max": hi, "triangles": 1}
        for k, (lo, hi) in enumerate(boxes)
    ]
    return {"charts": charts, "meshes": [{"mesh": mesh, "uv_fingerprint": fingerprint}]}


def test_mip_chain_halves_down_to_one_texel_and_keeps_the_mean():
    image = np.random.default_rng(0).random((20, 12, 3)).astype(np.float32)
    chain = mip_chain(image)
    assert [c.shape[:2] for c in chain] == [(20, 12), (10, 6), (5, 3), (3, 2), (2, 1), (1, 1)]
    even = mip_chain(image[:16, :8])
    assert np.allclose(even[-1][0, 0], image[:16, :8].mean(axis=(0, 1)), atol=1e-6)


def _random_case(seed: int, size: int = 24):
    """Random network outputs (3 charts, one of them untextured), two images with other wrap
    modes, and a perspective homography magnifying the network image about 3x."""
    rng = np.random.default_rng(seed)
    first = rng.random((64, 48, 3)).astype(np.float32)
    second = rng.random((16, 16, 3)).astype(np.float32)
    sources = {
        "Body": _source(first, ("repeat", "mirror")),
        "Cloth": _source(second, ("clamp", "black"), "Cloth"),
        "Plain": _source(None, name="Plain"),
    }
    table = _table([((0.1, 0.2), (0.6, 0.9)), ((-0.2, 0.3), (1.3, 1.1))])
    table["charts"][1]["mesh"] = "Cloth"
    table["charts"].append(
        {
            "index": 3,
            "mesh": "Plain",
            "tile": 1001,
            "uv_min": [0, 0],
            "uv_max": [1, 1],
            "triangles": 1,
        }
    )
    textures = ChartTextures.build(table, sources)
    logits = rng.normal(size=(4, size, size)) * 3
    probabilities = np.exp(logits) / np.exp(logits).sum(axis=0)
    coordinates = rng.uniform(-1.2, 1.2, (6, size, size)).astype(np.float32)
    homography = np.array([[3.1, 0.2, 5.0], [-0.1, 2.9, 3.0], [0.002, 0.001, 1.0]])
    region = (4, 2, 80, 76)
    coverage = (rng.random((76, 80)) > 0.2).astype(np.float32)
    return textures, homography, region, coverage, probabilities.astype(np.float32), coordinates


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kernel_matches_the_numpy_reference(seed):
    case = _random_case(seed)
    got = sample_textures(*case)
    ref = sample_textures(*case, kernel=False)
    np.testing.assert_array_equal(got.used, ref.used)
    np.testing.assert_array_equal(got.chart, ref.chart)
    used = got.used
    assert used.sum() > 500 and (~used & (case[3] > 0)).sum() > 100  # both kinds occur
    assert np.abs(got.colour - ref.colour).max() < KERNEL_TOLERANCE
    assert np.abs(got.st - ref.st).max() < KERNEL_TOLERANCE


def test_two_threads_sample_exactly_what_one_does(monkeypatch):
    from rigspace.sdk import texturing

    case = _random_case(3)
    assert np.count_nonzero(case[3]) >= texturing.SPLIT_PIXELS  # the two-thread path
    split = sample_textures(*case)
    monkeypatch.setattr(texturing, "SPLIT_PIXELS", 10**9)
    whole = sample_textures(*case)
    for name in ("colour", "used", "st", "chart"):
        assert np.array_equal(getattr(split, name), getattr(whole, name)), name


def test_magnified_linear_coordinates_read_the_texture_exactly():
    """A chart whose coordinates are a linear ramp over the network image, magnified 4x: every
    frame pixel reads the texture at its own st, exactly (mip level 0), as the renderers would."""
    size, scale = 16, 4.0
    texture = np.random.default_rng(3).random((32, 32, 3)).astype(np.float32)
    textures = ChartTextures.build(_table([((0.0, 0.0), (1.0, 1.0))]), {"Body": _source(texture)})
    centres = (np.arange(size) + 0.5) / size * 2 - 1  # the box's [-1, 1] at pixel centres
    coordinates = np.stack(
        [
            np.broadcast_to(centres[None, :], (size, size)),
            np.broadcast_to(-centres[:, None], (size, size)),
        ]
    ).astype(np.float32)
    probabilities = np.zeros((2, size, size), np.float32)
    probabilities[1] = 1.0
    frame = int(size * scale)
    sample = sample_textures(
        textures, np.diag([scale, scale, 1.0]), (0, 0, frame, frame),
        np.ones((frame, frame), np.float32), probabilities, coordinates,
    )  # fmt: skip
    out, used = sample.colour, sample.used
    # Frame pixel centres map to network x = (j + 0.5) / scale: st = that / size, v flipped.
    x = (np.arange(frame) + 0.5) / scale / size
    st = np.stack(np.meshgrid(x, 1 - x), axis=-1).reshape(-1, 2)
    inside = (np.abs(st - 0.5) <= 0.5 - 0.5 / size).all(axis=1).reshape(frame, frame)
    expected = sample_bilinear(texture, st).reshape(frame, frame, 3)
    assert used.all()
    assert np.abs(out - expected)[inside].max() < 1e-5


def test_coordinates_are_never_blended_across_charts():
    """Two charts side by side whose coordinates disagree wildly outside their own pixels: every
    frame pixel reads only its chart's values."""
    size = 8
    texture = np.zeros((2, 2, 3), np.float32)
    texture[:, 0] = (1, 0, 0)  # left half red: u < 0.5
    texture[:, 1] = (0, 0, 1)  # right half blue
    source = _source(texture, ("clamp", "clamp"))
    textures = ChartTextures.build(
        _table([((0.0, 0.0), (0.5, 1.0)), ((0.5, 0.0), (1.0, 1.0))]), {"Body": source}
    )
    probabilities = np.zeros((3, size, size), np.float32)
    probabilities[1, :, :4], probabilities[2, :, 4:] = 1.0, 1.0
    coordinates = np.zeros((4, size, size), np.float32)
    coordinates[0], coordinates[2] = -0.5, 0.5  # each chart's own: inside its half
    coordinates[0, :, 4:], coordinates[2, :, :4] = 50.0, -50.0  # garbage where not seen
    sample = sample_textures(
        textures, np.diag([8.0, 8.0, 1.0]), (0, 0, 64, 64), np.ones((64, 64), np.float32),
        probabilities, coordinates,
    )  # fmt: skip
    out, used = sample.colour, sample.used
    np.testing.assert_array_equal(sample.chart[:, :32], 1)
    np.testing.assert_array_equal(sample.chart[:, 32:], 2)
    assert used.all()
    assert np.allclose(out[:, :32], (1, 0, 0)) and np.allclose(out[:, 32:], (0, 0, 1))


def test_unsure_and_untextured_pixels_are_left_to_the_albedo_branch():
    size = 4
    chart = {"tile": 1001, "uv_min": [0, 0], "uv_max": [1, 1], "triangles": 1}
    textures = ChartTextures.build(
        {
            "charts": [
                {"index": 1, "mesh": "Body", **chart},
                {"index": 2, "mesh": "Plain", **chart},
                {"index": 3, "mesh": "Body", **chart},
            ],
            "meshes": [],
        },
        {"Body": _source(np.ones((4, 4, 3), np.float32)), "Plain": _source(None, name="Plain")},
    )
    assert textures.untextured == ("Plain",)
    probabilities = np.zeros((4, size, size), np.float32)
    probabilities[1] = 1.0
    # Most likely chart 1, but with under CHART_CONFIDENCE of the charts' probability: unsure.
    probabilities[:, 0, 0] = (0.1, 0.4, 0.2, 0.3)
    probabilities[:, 3, 3] = (0.0, 0.0, 1.0, 0.0)  # the untextured chart
    sample = sample_textures(
        textures, np.eye(3), (0, 0, size, size), np.ones((size, size), np.float32),
        probabilities, np.zeros((6, size, size), np.float32),
    )  # fmt: skip
    assert not sample.used[0, 0] and not sample.used[3, 3]
    assert sample.used.sum() == size * size - 2


def test_chart_borders_follow_the_interpolated_probabilities():
    """Two charts meeting between network pixels: upsampled 8x, the border lies where their
    interpolated probabilities cross, not on the network's pixel squares (a staircase)."""
    textures = ChartTextures.build(
        _table([((0, 0), (1, 1)), ((0, 0), (1, 1))]),
        {"Body": _source(np.ones((4, 4, 3), np.float32))},
    )
    size, scale = 4, 8
    probabilities = np.zeros((3, size, size), np.float32)
    # Chart 1's probability falls from 1 to 0 along x, sloped by the row: a diagonal border.
    for i in range(size):
        for j in range(size):
            p = np.clip(0.5 + (1.5 - j) * 0.5 + (i - 1.5) * 0.25, 0.0, 1.0)
            probabilities[1, i, j], probabilities[2, i, j] = p, 1.0 - p
    homography = np.diag([scale, scale, 1.0])
    frame = size * scale
    for kernel in (True, False):
        sample = sample_textures(
            textures, homography, (0, 0, frame, frame), np.ones((frame, frame), np.float32),
            probabilities, np.zeros((4, size, size), np.float32), kernel=kernel,
        )  # fmt: skip
        # Where chart 1 ends on each frame row: it moves by frame pixels, not by 8 at a time.
        ends = [int(np.argmax(row != 1)) for row in sample.chart[4:-4]]
        assert len(set(ends)) > size and all(np.diff(ends) >= 0)


def test_charts_of_other_uvs_are_refused():
    source = _source(np.ones((4, 4, 3), np.float32))
    with pytest.raises(TextureMismatch, match="other uvs"):
        ChartTextures.build(_table([((0, 0), (1, 1))], fingerprint="0" * 64), {"Body": source})
    with pytest.raises(TextureMismatch, match="is not there"):
        ChartTextures.build(_table([((0, 0), (1, 1))], mesh="Gone"), {"Body": source})


def test_sharpened_coverage_has_a_one_pixel_edge_at_the_same_place():
    """A disc's coverage at 32x32 upsampled 8x is a ramp 8 pixels wide; sharpened, it is one
    pixel wide and its area (where the edge is) stays the disc's."""
    import cv2

    small = 32
    y, x = np.mgrid[0:small, 0:small] + 0.5
    disc = np.clip(10.0 - np.hypot(x - 16, y - 16) + 0.5, 0, 1).astype(np.float32)
    big = cv2.resize(disc, (256, 256), interpolation=cv2.INTER_LINEAR)
    scale = magnification(np.diag([8.0, 8.0, 1.0]), (0, 0, 256, 256))
    assert scale == pytest.approx(8.0)
    sharp = sharpen_coverage(big, scale)
    partial = lambda c: int(((c > 0.02) & (c < 0.98)).sum())  # noqa: E731
    assert partial(sharp) < partial(big) / 4
    assert abs(sharp.sum() - np.pi * 80**2) / (np.pi * 80**2) < 0.02
    # Without magnification, coverage is kept as it is: a limb thinner than a pixel, and a
    # region one pixel wide, too.
    np.testing.assert_array_equal(sharpen_coverage(disc, 1.0), disc)
    thin = np.full((1, 5), 0.4, np.float32)
    np.testing.assert_array_equal(sharpen_coverage(thin, 1.0), thin)
    assert sharpen_coverage(thin, 2.0)[0, 0] == pytest.approx(0.3)  # weaker, not erased


def test_colour_is_premultiplied_by_the_coverage_it_returns():
    """The albedo branch's alpha is a network pixel wider than the geometry's mask (as the film
    character's are): the colour, textured or the albedo branch's, is premultiplied by the
    coverage returned, never more (before: by the wider alpha, a pale halo lit around every
    silhouette), and the straight colour inside is the branch's, or the texture's."""
    size, scale = 32, 4.0
    y, x = np.mgrid[0:size, 0:size] + 0.5
    r = np.hypot(x - 16, y - 16)
    mask = np.clip(9.0 - r + 0.5, 0, 1).astype(np.float32)[None]  # the geometry: radius 9
    alpha = np.clip(11.0 - r + 0.5, 0, 1).astype(np.float32)[None]  # the albedo branch: 11
    straight = np.array([0.8, 0.6, 0.4], np.float32)
    out = {"mask": mask, "alpha": alpha, "albedo": alpha * straight[:, None, None]}
    homography = np.diag([scale, scale, 1.0])
    frame = int(size * scale)
    region = (0, 0, frame, frame)
    warp = region_warper(homography, region)
    coverage = np.clip(warp(mask)[..., 0], 0.0, 1.0)  # as the runtime warps the geometry's
    colour, sharp, _ = display_colour(out, homography, region, coverage, None)
    assert (colour <= sharp[..., None] + 1e-6).all()
    inside = sharp > 0.5
    np.testing.assert_allclose(
        colour[inside] / sharp[inside][:, None],
        np.broadcast_to(straight, (int(inside.sum()), 3)),
        atol=1e-5,
    )
    # Textured: the texture's colour, premultiplied by the same coverage.
    textures = ChartTextures.build(
        _table([((0.0, 0.0), (1.0, 1.0))]), {"Body": _source(np.ones((4, 4, 3), np.float32))}
    )
    probabilities = np.zeros((2, size, size), np.float32)
    probabilities[1] = 1.0
    out.update(chart=probabilities, uv=np.zeros((2, size, size), np.float32))
    colour, sharp, info = display_colour(out, homography, region, coverage, textures)
    assert info["sample"].used[inside].all()
    np.testing.assert_allclose(colour, np.repeat(sharp[..., None], 3, axis=-1), atol=1e-6)
    # Unlit (the coverage is the alpha): the branch's own edge, its straight colour inside.
    unlit = {"alpha": out["alpha"], "albedo": out["albedo"]}
    alpha_coverage = np.clip(warp(alpha)[..., 0], 0.0, 1.0)
    colour, sharp, _ = display_colour(unlit, homography, region, alpha_coverage, None)
    assert (colour <= sharp[..., None] + 1e-6).all() and (sharp > 0.5).sum() > inside.sum()
    wide = sharp > 0.5
    np.testing.assert_allclose(
        colour[wide] / sharp[wide][:, None],
        np.broadcast_to(straight, (int(wide.sum()), 3)),
        atol=1e-5,
    )


def test_magnification_is_the_local_scale_of_the_homography():
    turned = np.array([[0, -3.0, 10], [3.0, 0, 5], [0, 0, 1]])
    assert magnification(turned, (0, 0, 40, 30)) == pytest.approx(3.0)
    # Perspective: the scale where the region is.
    tilted = np.array([[2.0, 0, 0], [0, 2.0, 0], [0.01, 0, 1]])
    near, far = (magnification(tilted, (x, 0, 2, 2)) for x in (0, 100))
    assert near > far


def test_a_degenerate_homography_sharpens_nothing():
    """A billboard seen edge-on in a viewport of a few pixels gives a singular or non-finite
    homography: no sharpening, and no NaN coverage (hypothesis found both)."""
    singular = np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 1]])
    assert magnification(singular, (0, 1, 1, 3)) == 1.0
    at_infinity = np.array([[1.0, 0, 0], [0, 1, 0], [1, 0, 0]])
    assert magnification(at_infinity, (0, 0, 1, 5)) == 1.0
    coverage = np.array([[0.3, 0.8]], np.float32)
    np.testing.assert_array_equal(
        sharpen_coverage(coverage, magnification(singular, (0, 0, 2, 1))), coverage
    )


def test_outputs_that_disagree_with_the_charts_are_refused():
    textures = ChartTextures.build(
        _table([((0, 0), (1, 1))]), {"Body": _source(np.ones((4, 4, 3), np.float32))}
    )
    with pytest.raises(TextureMismatch, match=r"charts\.json has 1 charts"):
        sample_textures(
            textures, np.eye(3), (0, 0, 4, 4), np.ones((4, 4), np.float32),
            np.ones((3, 4, 4), np.float32), np.zeros((2, 4, 4), np.float32),
        )  # fmt: skip


def test_characters_of_one_asset_share_their_mip_chains():
    """A crowd: each character decodes its own copy of the textures; the packed mip chains
    (the sampler's memory) are one set while any of them uses it."""
    image = np.random.default_rng(3).random((32, 16, 3)).astype(np.float32)
    first = ChartTextures.build(_table([((0, 0), (1, 1))]), {"Body": _source(image.copy())})
    second = ChartTextures.build(_table([((0, 0), (1, 1))]), {"Body": _source(image.copy())})
    assert second.texels is first.texels
    other = ChartTextures.build(_table([((0, 0), (1, 1))]), {"Body": _source(image[::-1].copy())})
    assert other.texels is not first.texels and not np.array_equal(other.texels, first.texels)


def test_the_kernel_s_most_likely_chart_is_numpy_s_argmax_ties_included():
    from rigspace.sdk.texture_kernel import _argmax

    rng = np.random.default_rng(5)
    probabilities = rng.random((29, 40, 30)).astype(np.float32)
    probabilities[:, :5] = 0.25  # every chart tied: the first wins, as numpy's argmax
    probabilities[3, 5:8] = probabilities[7, 5:8] = 2.0  # two tied at the top
    compiled = np.array([[_argmax(probabilities, i, j) for j in range(30)] for i in range(40)])
    assert np.array_equal(compiled, probabilities.argmax(axis=0))
    assert np.all(compiled[:5] == 0) and np.all(compiled[5:8] == 3)

"""Per-map error metrics (numpy only): albedo PSNR and SSIM, mask IoU, depth MAE, normal angle."""

from __future__ import annotations

import math

import cv2
import numpy as np

from rigspace.sdk.render import Maps

MASK_THRESHOLD = 0.5
"""Coverage at or above which a pixel counts as the character's (half covered counts)."""

SSIM_SIGMA = 1.5
"""Gaussian window of SSIM (Wang et al. 2004, section III-C): sigma 1.5 pixels, 11x11 taps."""
SSIM_WINDOW = 11
SSIM_K1 = 0.01
SSIM_K2 = 0.03
"""SSIM's stabilising constants (Wang et al. 2004, eq. 7 and 9), for data range 1."""


def _f64(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


def psnr(
    pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None, peak: float = 1.0
) -> float:
    """Peak signal-to-noise ratio in dB: 10 log10(peak^2 / MSE).

    The MSE is over every pixel and channel, or, with `mask` ((H,W), same height and width),
    over every channel of the pixels where mask > 0 only. An exact match gives +inf; an
    empty mask gives nan. For albedo the maps compare as stored: premultiplied R,G,B over
    the whole image, so a wrong silhouette costs PSNR too (the background is black in both).
    """
    error = (_f64(pred) - _f64(target)) ** 2
    if mask is not None:
        error = error[np.asarray(mask) > 0]
    if error.size == 0:
        return math.nan
    mse = float(error.mean())
    return math.inf if mse == 0.0 else 10.0 * math.log10(peak * peak / mse)


def ssim(pred: np.ndarray, target: np.ndarray) -> float:
    """Structural similarity (Wang et al. 2004) of (H,W) or (H,W,C) images, data range 1.

    Local statistics under an 11x11 Gaussian window of sigma 1.5 (eq. 13-15, no sample
    covariance correction), K1 = 0.01, K2 = 0.03. The SSIM map is averaged over the pixels
    whose window lies inside the image (Wang's "valid" filtering, as scikit-image crops it)
    and then over channels. Images smaller than the window average every pixel, with
    borders mirrored (cv2.BORDER_REFLECT). Identical images give exactly 1.
    """
    x, y = _f64(pred), _f64(target)
    if x.shape != y.shape:
        raise ValueError(f"ssim needs images of one shape, got {x.shape} and {y.shape}.")
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    c1, c2 = SSIM_K1**2, SSIM_K2**2  # (K L)^2 with L = 1

    def blur(a: np.ndarray) -> np.ndarray:
        # float64: sigma^2 = E[x^2] - E[x]^2 cancels badly in float32 for near-flat patches.
        out = cv2.GaussianBlur(
            a, (SSIM_WINDOW, SSIM_WINDOW), SSIM_SIGMA, borderType=cv2.BORDER_REFLECT
        )
        return out.reshape(a.shape)  # cv2 drops a trailing channel axis of size 1

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x * mu_x
    var_y = blur(y * y) - mu_y * mu_y
    cov = blur(x * y) - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / (
        (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    )
    r = SSIM_WINDOW // 2
    if min(x.shape[:2]) >= SSIM_WINDOW:
        ssim_map = ssim_map[r:-r, r:-r]
    return float(ssim_map.mean())


def mask_iou(
    pred_mask: np.ndarray, target_mask: np.ndarray, threshold: float = MASK_THRESHOLD
) -> float:
    """Intersection over union of the masks binarised at coverage >= threshold.

    Two empty masks agree perfectly: IoU 1.
    """
    p = np.asarray(pred_mask) >= threshold
    t = np.asarray(target_mask) >= threshold
    union = np.count_nonzero(p | t)
    return 1.0 if union == 0 else np.count_nonzero(p & t) / union


def depth_mae(
    pred_depth: np.ndarray,
    target_depth: np.ndarray,
    target_mask: np.ndarray,
    character_height: float,
) -> tuple[float, float]:
    """Mean absolute depth error in scene units, and as % of the character's height.

    Over the pixels inside the target mask (coverage >= MASK_THRESHOLD) where both depths
    are finite: a pixel the prediction leaves empty (+inf) is the mask IoU's to count, not
    an infinite depth error. No such pixel gives (nan, nan).
    """
    p, t = _f64(pred_depth), _f64(target_depth)
    inside = (np.asarray(target_mask) >= MASK_THRESHOLD) & np.isfinite(p) & np.isfinite(t)
    if not inside.any():
        return math.nan, math.nan
    mae = float(np.abs(p[inside] - t[inside]).mean())
    return mae, 100.0 * mae / character_height


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per vector, the angle in degrees between (..., 3) vectors `a` and `b`: atan2(|a x b|,
    a . b), which needs no clipping of the dot product and, unlike arccos, stays exact near 0
    (one float32 ulp below 1 is already 0.02 degrees through arccos). Scaling either vector
    leaves it unchanged."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.einsum("...i,...i->...", a, b)))


def normal_angle_error(
    pred: np.ndarray, target: np.ndarray, target_mask: np.ndarray
) -> tuple[float, float]:
    """Mean and median angle in degrees between (H,W,3) normals inside the target mask.

    Both normals are normalised first; pixels where either has zero length (a map's
    "empty") are left out, as are pixels outside the mask (coverage < MASK_THRESHOLD).
    The angle is angle_deg's (atan2: exact near 0). No such pixel gives (nan, nan).
    """
    a, b = _f64(pred), _f64(target)
    la, lb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    inside = (np.asarray(target_mask) >= MASK_THRESHOLD) & (la > 0) & (lb > 0)
    if not inside.any():
        return math.nan, math.nan
    a = a[inside] / la[inside, None]
    b = b[inside] / lb[inside, None]
    angle = angle_deg(a, b)
    return float(angle.mean()), float(np.median(angle))


METRICS = (
    "albedo_psnr",
    "albedo_ssim",
    "mask_iou",
    "depth_mae",
    "depth_mae_pct",
    "normal_mean_deg",
    "normal_median_deg",
)
"""The keys of map_metrics, in report order."""


def map_metrics(pred: Maps, target: Maps, character_height: float) -> dict[str, float]:
    """Every metric of one predicted frame against its ground truth (keys: METRICS).

    Albedo is compared premultiplied, as stored, over the whole image (see psnr); depth is in
    scene units and `character_height` (scene units) turns its error into a percentage.
    """
    for name in ("albedo", "normal", "depth", "mask"):
        p, t = getattr(pred, name), getattr(target, name)
        if np.shape(p) != np.shape(t):
            raise ValueError(
                f"predicted {name} has shape {np.shape(p)}, the ground truth {np.shape(t)}."
            )
    mae, mae_pct = depth_mae(pred.depth, target.depth, target.mask, character_height)
    mean_deg, median_deg = normal_angle_error(pred.normal, target.normal, target.mask)
    return {
        "albedo_psnr": psnr(pred.albedo, target.albedo),
        "albedo_ssim": ssim(pred.albedo, target.albedo),
        "mask_iou": mask_iou(pred.mask, target.mask),
        "depth_mae": mae,
        "depth_mae_pct": mae_pct,
        "normal_mean_deg": mean_deg,
        "normal_median_deg": median_deg,
    }


TEXTURE_METRICS = ("chart_accuracy", "uv_texels_median", "uv_texels_p90")
"""The keys of texture_metrics: how well a texture head places the texture."""


def texture_metrics(pred: Maps, target: Maps, texels_per_st: np.ndarray) -> dict[str, float]:
    """Where the target shows a chart whose texture the scene has (coverage >= MASK_THRESHOLD):
    the share of those pixels whose predicted chart is the target's, and where it is, how far
    the predicted texture coordinates land from the true ones in texels of that chart's
    texture (`texels_per_st`: (K+1, 2) texels per unit of s and t, nan for a chart without a
    texture; ChartTextures.texels_per_st): the median and the 90th percentile. nan where the
    maps carry no charts or no such pixel exists."""
    nothing = dict.fromkeys(TEXTURE_METRICS, math.nan)
    if pred.chart is None or pred.uv is None or target.chart is None or target.uv is None:
        return nothing
    if pred.chart.shape != target.chart.shape:
        raise ValueError(
            f"predicted charts have shape {pred.chart.shape}, the ground truth {target.chart.shape}."
        )
    chart = np.asarray(target.chart, np.int64)
    scale = np.asarray(texels_per_st, np.float64)
    textured = np.isfinite(scale[np.clip(chart, 0, len(scale) - 1)]).all(axis=-1)
    shown = (target.mask >= MASK_THRESHOLD) & (chart > 0) & (chart < len(scale)) & textured
    if not shown.any():
        return nothing
    right = shown & (np.asarray(pred.chart) == chart)
    out = {"chart_accuracy": float(right.sum() / shown.sum())}
    if not right.any():
        return out | {"uv_texels_median": math.nan, "uv_texels_p90": math.nan}
    delta = (_f64(pred.uv)[right] - _f64(target.uv)[right]) * scale[chart[right]]
    texels = np.linalg.norm(delta, axis=-1)
    return out | {
        "uv_texels_median": float(np.median(texels)),
        "uv_texels_p90": float(np.percentile(texels, 90)),
    }

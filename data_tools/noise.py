"""Kinect-v1-like depth noise for synthetic depth maps.

Model (Nguyen, Izadi & Lovell, "Modeling Kinect Sensor Noise for Improved 3D Reconstruction
and Tracking", 3DIMPVT 2012), with z the depth in metres and theta the angle between the
viewing ray and the surface normal:

- axial:   sigma_z = 0.0012 + 0.0019 (z - 0.4)^2                       for theta <= 60 deg
           sigma_z = 0.0012 + 0.0019 (z - 0.4)^2 + 0.0001/sqrt(z) * theta^2/(pi/2 - theta)^2
                                                                          for theta > 60 deg
- lateral: sigma_L = 0.8 + 0.035 theta/(pi/2 - theta) pixels.

The paper's sigma_z is the total spread it measured, which already contains the disparity
quantisation, so the Gaussian part is drawn with variance sigma_z^2 - q^2/12 (q the local
depth step of one disparity step) before quantising: the total then follows the formula.

Steps, in order:
1. projector shadow: the IR projector sits `baseline_m` along +x; camera pixels whose surface
   point it cannot see (a nearer surface covers it in the projector's view) get no depth, a
   band beside the left of foreground objects;
2. lateral noise: each pixel samples its depth at a position jittered by sigma_L (spatially
   correlated over ~1 px); only where that position falls across a depth discontinuity does
   the pixel take the other side's depth, so silhouettes become ragged while smooth surfaces
   keep their axial noise alone (the paper measured lateral noise at edges);
3. axial Gaussian noise, then Kinect's disparity quantisation: disparity d = f b / z in steps
   of 1/8 pixel, b = 7.5 cm, f = fx of the intrinsics at the sensor's native 640-pixel width
   (fx * 640 / width; f = fx at the default 640x480), so the depth resolution (~3 mm at 1 m)
   does not change with the rendered image size;
4. dropouts: incidence beyond 80 deg, a random share of pixels next to depth discontinuities
   and silhouettes, and depth outside the working range 0.4-4.5 m.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from surfelwarp.geometry.camera import Intrinsics


@dataclass(frozen=True)
class KinectNoiseParams:
    axial_base_m: float = 0.0012
    axial_quadratic_per_m: float = 0.0019
    axial_offset_m: float = 0.4
    angle_term_m: float = 0.0001               # times 1/sqrt(z / 1 m)
    angle_onset_rad: float = np.pi / 3
    lateral_base_px: float = 0.8
    lateral_angle_px: float = 0.035
    lateral_correlation_px: float = 1.0
    lateral_max_px: float = 3.0
    baseline_m: float = 0.075
    disparity_step_px: float = 1.0 / 8.0
    native_width_px: int = 640                 # disparity is measured in pixels of this width
    grazing_dropout_rad: float = np.deg2rad(80.0)
    edge_jump_ratio: float = 0.02              # > 2 % of the depth per pixel apart: an edge
    edge_dropout_probability: float = 0.3
    min_range_m: float = 0.4
    max_range_m: float = 4.5


def _angle_ratio(theta: np.ndarray) -> np.ndarray:
    theta = np.minimum(theta, np.pi / 2 - 1e-3)
    return theta / (np.pi / 2 - theta)


def axial_sigma(z: np.ndarray, theta: np.ndarray, p: KinectNoiseParams = KinectNoiseParams()) -> np.ndarray:
    """Axial standard deviation in metres at depth z (m) and incidence theta (rad)."""
    z = np.asarray(z, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    sigma = p.axial_base_m + p.axial_quadratic_per_m * (z - p.axial_offset_m) ** 2
    extra = p.angle_term_m / np.sqrt(np.maximum(z, 1e-6)) * _angle_ratio(theta) ** 2
    return sigma + np.where(theta > p.angle_onset_rad, extra, 0.0)


def lateral_sigma_px(theta: np.ndarray, p: KinectNoiseParams = KinectNoiseParams()) -> np.ndarray:
    return p.lateral_base_px + p.lateral_angle_px * _angle_ratio(np.asarray(theta, dtype=np.float64))


def disparity_quantise(z: np.ndarray, focal_px: float, p: KinectNoiseParams = KinectNoiseParams()) -> np.ndarray:
    """Depth snapped to the nearest 1/8-pixel disparity step; 0 stays 0."""
    fb = focal_px * p.baseline_m
    with np.errstate(divide="ignore", invalid="ignore"):
        steps = np.rint(fb / z / p.disparity_step_px)
        out = fb / (steps * p.disparity_step_px)
    return np.where((z > 0) & (steps > 0), out, 0.0)


def projector_shadow(depth: np.ndarray, focal_px: float, p: KinectNoiseParams = KinectNoiseParams()) -> np.ndarray:
    """Pixels whose surface point a nearer surface hides from the projector (bool mask)."""
    h, w = depth.shape
    v, u = np.nonzero(depth > 0)
    if len(v) == 0:
        return np.zeros_like(depth, dtype=bool)
    z = depth[v, u].astype(np.float64)
    # Same orientation, shifted by the baseline: the projector sees the point at u - f b / z.
    up = np.rint(u - focal_px * p.baseline_m / z).astype(np.int64)
    up -= up.min()
    key = v * (up.max() + 1) + up
    nearest = np.full(h * (up.max() + 1), np.inf)
    np.minimum.at(nearest, key, z)
    # Neighbours in one projector pixel differ by up to tan(incidence)/f of the depth on a
    # surface the projector still lights (incidence below the grazing limit): not shadow.
    hidden = z > nearest[key] * (1.0 + np.tan(p.grazing_dropout_rad) / focal_px)
    mask = np.zeros_like(depth, dtype=bool)
    mask[v[hidden], u[hidden]] = True
    return mask


def _correlated_normal(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Unit-variance Gaussian field smoothed over ~sigma_px."""
    field = rng.standard_normal(shape).astype(np.float32)
    if sigma_px <= 0:
        return field
    k = cv2.getGaussianKernel(2 * int(np.ceil(3 * sigma_px)) + 1, sigma_px)
    return cv2.sepFilter2D(field, -1, k, k, borderType=cv2.BORDER_REFLECT) / np.float32(np.sum(k * k))


def depth_edges(depth: np.ndarray, ratio: float) -> np.ndarray:
    """Valid pixels next to no depth, or whose 3x3 neighbourhood (2 px across) spans more
    than `ratio` of the depth per pixel."""
    big = np.where(depth > 0, depth, np.float32(1e6)).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    hi = cv2.dilate(big, kernel, borderType=cv2.BORDER_REPLICATE)
    lo = cv2.erode(depth.astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    return (depth > 0) & ((hi - lo) > 2 * ratio * depth)


def kinect_noise(depth: np.ndarray, cos_incidence: np.ndarray, intrinsics: Intrinsics, rng: np.random.Generator,
                 p: KinectNoiseParams = KinectNoiseParams()) -> np.ndarray:
    """Noisy float32 depth (metres, 0 = no measurement) from clean depth and incidence cosines."""
    h, w = depth.shape
    f = intrinsics.fx
    f_native = f * p.native_width_px / w
    depth = np.where(projector_shadow(depth, f, p), np.float32(0), depth).astype(np.float32)
    theta = np.arccos(np.clip(cos_incidence, 0.0, 1.0)).astype(np.float32)

    # No measurement: no surface to be grazing; the jitter is capped where theta nears 90 deg.
    sigma_l = np.minimum(lateral_sigma_px(np.where(depth > 0, theta, 0.0), p), p.lateral_max_px)
    vv, uu = np.mgrid[0:h, 0:w]
    su = np.clip(np.rint(uu + sigma_l * _correlated_normal(rng, (h, w), p.lateral_correlation_px)), 0, w - 1).astype(np.intp)
    sv = np.clip(np.rint(vv + sigma_l * _correlated_normal(rng, (h, w), p.lateral_correlation_px)), 0, h - 1).astype(np.intp)
    other = depth[sv, su]
    # A smooth surface changes by up to edge_jump_ratio of the depth per pixel; more is an edge.
    reach = np.maximum(1.0, np.hypot(su - uu, sv - vv))
    across = np.abs(other - depth) > p.edge_jump_ratio * reach * np.maximum(other, depth)
    z = np.where(across, other, depth)
    theta = np.where(across, theta[sv, su], theta)

    drop = theta > p.grazing_dropout_rad
    drop |= depth_edges(z, p.edge_jump_ratio) & (rng.random((h, w)) < p.edge_dropout_probability)

    sigma = axial_sigma(z, theta, p)
    step = z.astype(np.float64) ** 2 * p.disparity_step_px / (f_native * p.baseline_m)
    sigma_gauss = np.sqrt(np.maximum(sigma ** 2 - step ** 2 / 12.0, (0.25 * sigma) ** 2))
    noisy = disparity_quantise(np.where(z > 0, z + sigma_gauss * rng.standard_normal((h, w)), 0.0), f_native, p)
    drop |= (noisy < p.min_range_m) | (noisy > p.max_range_m)
    return np.where(drop | (z <= 0), 0.0, noisy).astype(np.float32)

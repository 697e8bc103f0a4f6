"""Depth fusion at the live frame and model cleanup (SurfelWarp Sec. VI-A and VI-D).

The live surfels are drawn as unsized points into a supersampled index map (see
render/index_map.py); each depth pixel searches the window of fine pixels it covers for one live
surfel to fuse into (Eq. 5). Only `live_*` geometry is touched here: the caller inverse-warps
to S_ref afterwards. Removal follows Keller et al. 2013: long-unstable surfels and near
duplicates of a neighbour on the index map.

The index map must have been rendered from the model's live surfels, all of them and in
model order, so that a map index is a model index.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from surfelwarp.geometry.camera import KINECT_AXIAL_NOISE, axial_noise_sigma_m
from surfelwarp.methods.surfelwarp.fusion_kernels import best_in_windows, fuse_rows, mark_covered, mark_redundant
from surfelwarp.methods.surfelwarp.surfels import SurfelModel
from surfelwarp.preprocess import CameraObservation
from surfelwarp.render.base import FAR_M, NEAR_M
from surfelwarp.render.index_map import FusionMaps


@dataclass(frozen=True)
class FusionParams:
    # Table 1 says 1 mm, below the Kinect's own noise (~1.5 mm axial at 1 m) and the lateral
    # spread of one depth pixel (~1.7 mm at 1 m). Share of valid pixels fused, 1 / 3 / 10 mm:
    # synthetic Kinect noise, exact pose, 640x480: 0.69 / 0.99 / 0.997; 7-Scenes frames 1, 5, 10
    # against frame 0 with ground-truth poses: 0.03-0.09 / 0.34-0.47 / 0.65-0.81. Every miss
    # is appended as a duplicate, so 1 cm; it still rejects a surface 11 mm off.
    distance_threshold_m: float = 0.01
    # ... and at least this many standard deviations of the sensor's axial noise at the pixel's
    # depth (0: the fixed gate alone). The fixed gate suits ~1 m; 7-Scenes reaches 2.7 m, where
    # Kinect noise is 11 mm: with 1 cm alone 10 % of its pixels failed the gate against the
    # previous frame's model at the right pose (distance median 2.1 mm, 95th percentile 10.8 mm)
    # and were appended as duplicates.
    distance_noise_sigmas: float = 3.0
    axial_noise: tuple[float, ...] = KINECT_AXIAL_NOISE   # a, b, z0 of camera.axial_noise_sigma_m
    normal_threshold: float = 0.85          # delta_normal: min dot(n_depth, n_surfel)
    stable_confidence: float = 10.0         # delta_stable
    unstable_frames: int = 30               # t_low_confid
    window: int = 4                         # search window on the index map, fine pixels a side
    # Redundancy (Keller et al.): a surfel within this fraction of the smaller radius of a
    # neighbour on the index map, with normals closer than this dot product, is a duplicate.
    redundant_distance_ratio: float = 0.5
    redundant_normal_threshold: float = 0.95
    redundant_neighbourhood_px: int = 1     # fine pixels each way (1 -> 3x3)
    # Live surfels the camera saw through (tracking/free_space.py, with the tracker's
    # silhouette parameters) by more than this are removed (inf or 1e9: none). Nearer ones are left to
    # the tracker's free-space term, which pulls them back: carved, a sheet's overhanging edge
    # would no longer hold the model in place (free sheet: EPE 95 mm carving at 0, 22 mm at 1 cm).
    carve_beyond_m: float = 0.01
    # A depth pixel that fused into no surfel is appended only where the model has no surface:
    # no live surfel facing the same side within the distance gate (widened by the pixels'
    # footprint) in the pixels coverage_px around. Depth normals at 2-3 m fail the normal gate
    # against a surfel in place, and a stretched model leaves single pixels between its
    # surfels: neither is new surface (False: every unmatched pixel is appended, the paper's).
    append_only_uncovered: bool = True
    coverage_px: int = 1
    # Fusion moves a surfel's reference position only along its normal: depth measures where
    # the surface is, not which material point a pixel shows, so the tangential part of the
    # inverse-warped fused position is the tracker's slide along the surface, and taking it
    # would make the reference follow every slide (False: the paper's Eq. 3 as it is).
    reference_along_normal: bool = True

    ZERO_OK = {"axial_noise", "normal_threshold", "stable_confidence", "unstable_frames", "redundant_distance_ratio",
               "redundant_normal_threshold", "redundant_neighbourhood_px", "carve_beyond_m", "coverage_px"}
    UNIT = {"normal_threshold", "redundant_normal_threshold"}
    # carve_beyond_m has no bound: a config file cannot say inf, so a huge value is its "off".
    AT_MOST = {"window": 16, "redundant_neighbourhood_px": 16, "coverage_px": 16, "carve_beyond_m": None}


class Correspondences(NamedTuple):
    """Depth pixel (row, col) -> model surfel index; each surfel appears at most once."""
    pixel_rows: np.ndarray     # (M,) int64
    pixel_cols: np.ndarray     # (M,) int64
    surfel_index: np.ndarray   # (M,) int64


def distance_gate_m(depth_m: np.ndarray, params: FusionParams = FusionParams()) -> np.ndarray:
    """The fusion distance gate at each depth: the fixed threshold, widened to
    distance_noise_sigmas times the axial noise sigma(z) where that is larger (float32)."""
    sigma = axial_noise_sigma_m(np.asarray(depth_m, np.float32), params.axial_noise)
    return np.maximum(np.float32(params.distance_threshold_m), np.float32(params.distance_noise_sigmas) * sigma)


def _window_origin(pixel: np.ndarray, supersample: int, window: int) -> np.ndarray:
    # Depth pixel r covers fine rows s*r .. s*r+s-1 (Intrinsics.supersampled keeps centres
    # aligned); a window of w fine pixels is centred on that block.
    return supersample * pixel + (supersample - window) // 2


def find_correspondences(maps: FusionMaps, obs: CameraObservation, live_confidence: np.ndarray,
                         params: FusionParams = FusionParams()) -> Correspondences:
    """For every valid depth pixel, the surfel in its index-map window passing the distance gate
    (distance_gate_m) and the normal gate with the highest confidence (ties: the closest).

    When windows overlap (window > supersample) a surfel chosen by several pixels stays with the
    closest of them (ties: the first in row-major order); the others get no correspondence.
    With the default window == supersample the windows tile the map and this never happens.
    """
    s, w = maps.supersample, params.window
    fine_h, fine_w = maps.index.shape
    if (fine_h, fine_w) != (s * obs.valid.shape[0], s * obs.valid.shape[1]):
        raise ValueError(f"index map {maps.index.shape} is not {s}x the depth map {obs.valid.shape}")
    pix = np.flatnonzero(obs.valid)
    rows, cols = np.divmod(pix, obs.valid.shape[1])
    best_k = np.empty(len(rows), np.int64)
    best_d2 = np.empty(len(rows), np.float32)
    vertex, normal = _depth_at(obs, pix)
    best_in_windows(maps.index, _window_origin(rows, s, w), _window_origin(cols, s, w), w,
                    np.ascontiguousarray(maps.points, np.float32), np.ascontiguousarray(maps.normals, np.float32),
                    vertex, normal, distance_gate_m(np.take(obs.depth_m, pix), params) ** 2,
                    np.float32(params.normal_threshold),
                    np.ascontiguousarray(live_confidence, np.float32), best_k, best_d2)
    found = best_k >= 0
    rows, cols, best_k, best_d2 = rows[found], cols[found], best_k[found], best_d2[found]
    if w > s:
        # Stable sort keeps row-major order among equal distances.
        order = np.lexsort((best_d2, best_k))
        first = np.r_[True, best_k[order][1:] != best_k[order][:-1]]
        keep = np.sort(order[first])
        rows, cols, best_k = rows[keep], cols[keep], best_k[keep]
    return Correspondences(rows, cols, best_k)


def fuse(model: SurfelModel, T_camera_to_world: np.ndarray, obs: CameraObservation,
         corr: Correspondences, time: int, params: FusionParams = FusionParams()
         ) -> tuple[SurfelModel, np.ndarray]:
    """Eq. 5: confidence-weighted averages of live position, normal (renormalised), radius and
    (with obs.color) colour, summed confidence, t_observed = time. Returns the new model and the
    (H, W) mask of fused pixels. The surfel indices in `corr` must be distinct
    (find_correspondences ensures it). fuse_reference's result, its per-surfel updates in one
    compiled pass (a twist-limb frame, 264k pairs with colour: 66 -> 19 ms)."""
    rows, cols, k = corr
    pix, depth_v, depth_n = _depth_in_world(obs, rows, cols, T_camera_to_world)
    out = {name: getattr(model, name).copy() for name in _FUSED}
    depth_color = np.zeros((0, 3), np.uint8) if obs.color is None else obs.color.reshape(-1, 3)
    fuse_rows(np.asarray(k, np.int64), pix, depth_v, depth_n, obs.confidence_map.reshape(-1),
              obs.radius_map.reshape(-1), depth_color, np.int32(time), *out.values())
    if obs.color is None:
        del out["color"], out["color_weight"]
    fused = np.zeros(obs.valid.shape, bool)
    fused[rows, cols] = True
    return replace(model, **out), fused


_FUSED = ("live_position", "live_normal", "radius", "confidence", "t_observed", "color", "color_weight")


def _depth_in_world(obs: CameraObservation, rows: np.ndarray, cols: np.ndarray, T_camera_to_world: np.ndarray):
    """The pixels' flat indices and their depth vertices and normals (n, 3) in world, float32
    (the weights are well conditioned and float64 costs here ~3x)."""
    T = np.asarray(T_camera_to_world, np.float64)
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    pix = rows * obs.valid.shape[1] + cols
    vertex, normal = _depth_at(obs, pix)
    return pix, vertex @ R.T + t, normal @ R.T


def _depth_at(obs: CameraObservation, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The depth vertices and normals (n, 3), camera frame, at flat pixel indices: row gathers
    by np.take, several times faster than fancy indexing."""
    return np.take(obs.vertex_map.reshape(-1, 3), pix, axis=0), np.take(obs.normal_map.reshape(-1, 3), pix, axis=0)


def fuse_reference(model: SurfelModel, T_camera_to_world: np.ndarray, obs: CameraObservation,
                   corr: Correspondences, time: int, params: FusionParams = FusionParams()
                   ) -> tuple[SurfelModel, np.ndarray]:
    """fuse in numpy, a pass an expression (what the tests compare it with)."""
    rows, cols, k = corr
    pix, depth_v, depth_n = _depth_in_world(obs, rows, cols, T_camera_to_world)
    c_depth = np.take(obs.confidence_map, pix)
    c_old = np.take(model.confidence, k)
    c_new = c_old + c_depth
    a = (c_old / np.maximum(c_new, np.float32(1e-30)))[:, None]
    b = (c_depth / np.maximum(c_new, np.float32(1e-30)))[:, None]

    position = model.live_position.copy()
    normal = model.live_normal.copy()
    radius = model.radius.copy()
    confidence = model.confidence.copy()
    t_observed = model.t_observed.copy()
    position[k] = a * np.take(model.live_position, k, axis=0) + b * depth_v
    n = a * np.take(model.live_normal, k, axis=0) + b * depth_n
    normal[k] = n / np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n))[:, None], 1e-12)
    radius[k] = a[:, 0] * np.take(model.radius, k) + b[:, 0] * np.take(obs.radius_map, pix)
    confidence[k] = c_new
    t_observed[k] = time

    fused = np.zeros(obs.valid.shape, bool)
    fused[rows, cols] = True
    return replace(model, live_position=position, live_normal=normal, radius=radius,
                   confidence=confidence, t_observed=t_observed, **_fused_color(model, obs, corr)), fused


def _fused_color(model: SurfelModel, obs: CameraObservation, corr: Correspondences) -> dict:
    """color and color_weight after fusing obs.color with the same confidence weights as the
    position; nothing changes without colour. The weight counts coloured observations only, so
    a surfel first seen in a frame without colour takes its first colour whole."""
    if obs.color is None:
        return {}
    rows, cols, k = corr
    c_depth = obs.confidence_map[rows, cols]
    w_old = model.color_weight[k]
    w_new = w_old + c_depth
    color, color_weight = model.color.copy(), model.color_weight.copy()
    # The average as a step toward the new colour: a whole step (w_old = 0) lands on it exactly.
    old = model.color[k]
    color[k] = old + (c_depth / np.maximum(w_new, np.float32(1e-30)))[:, None] * (obs.color[rows, cols] - old)
    color_weight[k] = w_new
    return {"color": color, "color_weight": color_weight}


def unmatched_depth_pixels(obs: CameraObservation, fused_pixel_mask: np.ndarray, maps: FusionMaps | None = None,
                           params: FusionParams = FusionParams()) -> np.ndarray:
    """(H, W) mask of valid depth pixels that fused into no surfel and, given the index map,
    that no live surfel covers (params.coverage_px): the append candidates."""
    unmatched = obs.valid & ~fused_pixel_mask
    if maps is None:
        return unmatched
    rows, cols = np.nonzero(unmatched)
    depth_v, depth_n = obs.vertex_map[rows, cols], obs.normal_map[rows, cols]
    # The gate, plus the footprint of the pixels reached across.
    z = obs.depth_m[rows, cols]
    max_d2 = (distance_gate_m(z, params) + np.sqrt(2) * params.coverage_px * z / obs.intrinsics.focal_px) ** 2
    covered = np.zeros(len(rows), bool)
    mark_covered(maps.index, maps.supersample, rows, cols, params.coverage_px, maps.points, maps.normals,
                 depth_v, depth_n, max_d2, covered)
    unmatched[rows[covered], cols[covered]] = False
    return unmatched


def unstable_mask(model: SurfelModel, time: int, params: FusionParams = FusionParams()) -> np.ndarray:
    """Surfels still below delta_stable more than t_low_confid frames after creation."""
    return (model.confidence < params.stable_confidence) & (time - model.t_init > params.unstable_frames)


def _surfel_pixels(model: SurfelModel, maps: FusionMaps, T_camera_to_world: np.ndarray | None):
    """(surfel, fine row, fine col) of the surfels on the map: the visible ones from the map
    itself, or, given the pose, every surfel in view by the renderer's rounding, hidden too."""
    if T_camera_to_world is None:
        fr, fc = np.nonzero(maps.index >= 0)
        return maps.index[fr, fc].astype(np.int64), fr, fc
    T = np.asarray(T_camera_to_world, np.float64)
    p = (model.live_position.astype(np.float64) - T[:3, 3]) @ T[:3, :3]
    intr = maps.intrinsics
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        fc = np.floor(intr.fx * p[:, 0] / z + intr.cx + 0.5)
        fr = np.floor(intr.fy * p[:, 1] / z + intr.cy + 0.5)
    h, w = maps.index.shape
    ok = (z > NEAR_M) & (z < FAR_M) & (fr >= 0) & (fr < h) & (fc >= 0) & (fc < w)
    j = np.flatnonzero(ok)
    return j, fr[j].astype(np.int64), fc[j].astype(np.int64)


def redundant_mask(model: SurfelModel, maps: FusionMaps, params: FusionParams = FusionParams(),
                   T_camera_to_world: np.ndarray | None = None) -> np.ndarray:
    """Near duplicates (Keller et al. 2013): surfel j and a surfel i on the same or an adjacent
    fine pixel of the index map, closer than redundant_distance_ratio * min(r_i, r_j) with
    dot(n_i, n_j) > redundant_normal_threshold. Of each such pair the one with lower confidence
    (ties: the higher index) is dropped, nothing is merged.

    Without the pose only surfels visible on the map are compared; with T_camera_to_world
    (of the camera the map was rendered from) surfels hidden behind the one on their own pixel
    are found too. A chain a~b~c may lose two surfels; the next frame's pass catches what a
    single pass leaves.
    """
    j, fr, fc = _surfel_pixels(model, maps, T_camera_to_world)
    drop = np.zeros(len(model), bool)
    mark_redundant(maps.index, j, fr, fc, params.redundant_neighbourhood_px, model.live_position,
                   model.live_normal, model.radius, model.confidence, np.float32(params.redundant_distance_ratio),
                   np.float32(params.redundant_normal_threshold), drop)
    return drop


def removal_mask(model: SurfelModel, maps: FusionMaps, time: int, params: FusionParams = FusionParams(),
                 T_camera_to_world: np.ndarray | None = None) -> np.ndarray:
    """Surfels to drop (Sec. VI-D): long-unstable ones and near duplicates on the index map."""
    return unstable_mask(model, time, params) | redundant_mask(model, maps, params, T_camera_to_world)


def remove(model: SurfelModel, mask: np.ndarray) -> SurfelModel:
    return model.select(~mask)

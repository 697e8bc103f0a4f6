"""How well the live model and the depth explain each other, from both sides.

The non-rigid RMS only averages over the pairs that were found: a model that slides along the
surface or off its edge keeps a small RMS over the pairs that remain. Two fractions see it:
- unsupported: of the model points that should be visible (in the image, facing the camera, not
  behind the observed surface), those with no valid depth within support_m in a window of
  window_px pixels around their projection (SurfelWarp Sec. VI-F's window search);
- unexplained: of the valid depth pixels, those with no model point projecting within the
  window at a depth within support_m of the pixel's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from surfelwarp.geometry.camera import Intrinsics


@dataclass(frozen=True)
class AlignmentParams:
    support_m: float = 0.01
    window_px: int = 1
    occlusion_margin_m: float = 0.01     # depth this far in front of a point occludes it
    image_margin_px: int = 12            # projections this close to the edge are not judged
    max_judged_points: int = 20_000      # the model side is a share: judged on an even subsample


@dataclass(frozen=True)
class Alignment:
    unsupported_fraction: float      # of the model points that should be visible
    unexplained_fraction: float      # of the valid depth pixels
    judged_points: int               # (of an even subsample of at most max_judged_points)
    valid_pixels: int


def _project(points: np.ndarray, intrinsics: Intrinsics, shape: tuple[int, int], margin: int):
    """Pixel (row, col) int64 of camera-frame points (N, 3) and whether it lies in the image
    at least `margin` pixels from its edge, in front of the camera."""
    h, w = shape
    z = points[:, 2]
    front = z > 1e-3
    zs = np.where(front, z, 1.0)
    col = np.rint(intrinsics.fx * points[:, 0] / zs + intrinsics.cx).astype(np.int64)
    row = np.rint(intrinsics.fy * points[:, 1] / zs + intrinsics.cy).astype(np.int64)
    inside = front & (col >= margin) & (col < w - margin) & (row >= margin) & (row < h - margin)
    return row, col, inside


def model_support(points: np.ndarray, normals: np.ndarray, depth_m: np.ndarray, vertex_map: np.ndarray,
                  valid: np.ndarray, intrinsics: Intrinsics, params: AlignmentParams = AlignmentParams()
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool each: camera-frame points (N, 3) that should be visible (judged), and those of
    them with depth support. model_support_reference's result with its window search compiled
    (its numpy passes took ~2 ms for 20k points)."""
    j, row, col, p, occluded = _judged(points, normals, depth_m, intrinsics, valid.shape, params)
    supported = np.zeros(len(j), bool)
    vertex = np.asarray(vertex_map)
    dtype = np.result_type(vertex.dtype, p.dtype)
    _supported(np.ascontiguousarray(vertex, dtype), np.ascontiguousarray(valid, bool), row, col,
               np.ascontiguousarray(p, dtype), params.window_px, dtype.type(params.support_m ** 2), supported)
    return _support_masks(len(points), j, occluded, supported)


def model_support_reference(points: np.ndarray, normals: np.ndarray, depth_m: np.ndarray, vertex_map: np.ndarray,
                            valid: np.ndarray, intrinsics: Intrinsics, params: AlignmentParams = AlignmentParams()
                            ) -> tuple[np.ndarray, np.ndarray]:
    """model_support in numpy passes, a window offset at a time (what the tests compare it with)."""
    h, w = valid.shape
    j, row, col, p, occluded = _judged(points, normals, depth_m, intrinsics, (h, w), params)
    supported = np.zeros(len(j), bool)
    r, max_d2 = params.window_px, params.support_m ** 2
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            y, x = np.clip(row + dy, 0, h - 1), np.clip(col + dx, 0, w - 1)
            d = vertex_map[y, x] - p
            supported |= valid[y, x] & (np.einsum("ij,ij->i", d, d) <= max_d2)
    return _support_masks(len(points), j, occluded, supported)


def _judged(points, normals, depth_m, intrinsics, shape, params):
    """The points in view and facing the camera (their indices j, pixels and positions), and
    which of them the observed depth occludes."""
    row, col, inside = _project(points, intrinsics, shape, params.image_margin_px)
    facing = np.einsum("ij,ij->i", normals, points) < 0
    j = np.flatnonzero(inside & facing)
    row, col, p = row[j], col[j], points[j]
    observed = depth_m[row, col]
    return j, row, col, p, (observed > 0) & (observed < p[:, 2] - params.occlusion_margin_m)


def _support_masks(n, j, occluded, supported):
    judged = np.zeros(n, bool)
    judged[j[~occluded]] = True
    out = np.zeros(n, bool)
    out[j[~occluded & supported]] = True
    return judged, out


@numba.njit(cache=True, nogil=True)
def _supported(vertex_map, valid, rows, cols, points, r, max_d2, out):
    """out[i]: a valid pixel within r of (rows[i], cols[i]) (clamped to the image) has its
    vertex within sqrt(max_d2) of points[i], the squares summed in the reference's order."""
    h, w = valid.shape
    for i in range(len(rows)):
        for dy in range(-r, r + 1):
            y = min(max(rows[i] + dy, 0), h - 1)
            for dx in range(-r, r + 1):
                x = min(max(cols[i] + dx, 0), w - 1)
                if valid[y, x]:
                    d0 = vertex_map[y, x, 0] - points[i, 0]
                    d1 = vertex_map[y, x, 1] - points[i, 1]
                    d2 = vertex_map[y, x, 2] - points[i, 2]
                    if d0 * d0 + d1 * d1 + d2 * d2 <= max_d2:
                        out[i] = True
                        break
            if out[i]:
                break


def explained_pixels(points: np.ndarray, vertex_map: np.ndarray, valid: np.ndarray, intrinsics: Intrinsics,
                     params: AlignmentParams = AlignmentParams()) -> np.ndarray:
    """(H, W) bool: valid depth pixels with a camera-frame model point (N, 3) projecting within
    the window at a depth within support_m of the pixel's (one point per pixel is kept: the
    last; a window pixel's lateral offset is a few millimetres, well inside the support).
    explained_pixels_reference's result in one compiled pass over the valid pixels (its numpy
    passes over the whole image took ~2 ms a frame)."""
    model_z, depth = _model_depth(points, vertex_map, intrinsics, params.window_px)
    explained = np.zeros(valid.shape, bool)
    dtype = np.result_type(model_z.dtype, depth.dtype)
    _explained(model_z, np.ascontiguousarray(depth, dtype), np.ascontiguousarray(valid, bool), params.window_px,
               dtype.type(params.support_m), explained)
    return explained


def explained_pixels_reference(points: np.ndarray, vertex_map: np.ndarray, valid: np.ndarray, intrinsics: Intrinsics,
                               params: AlignmentParams = AlignmentParams()) -> np.ndarray:
    """explained_pixels in numpy passes over the image, a window offset at a time."""
    h, w = valid.shape
    r = params.window_px
    model_z, depth = _model_depth(points, vertex_map, intrinsics, r)
    explained = np.zeros((h, w), bool)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            explained |= np.abs(model_z[dy:dy + h, dx:dx + w] - depth) <= params.support_m
    return explained & valid


def _model_depth(points, vertex_map, intrinsics, r):
    """The points' depth at their pixels (inf elsewhere) in an image padded by r, and the
    observed depth."""
    h, w = vertex_map.shape[:2]
    row, col, inside = _project(points, intrinsics, (h, w), 0)
    model_z = np.full((h + 2 * r, w + 2 * r), np.inf, np.float32)
    model_z[row[inside] + r, col[inside] + r] = points[inside, 2]
    return model_z, vertex_map[..., 2]


@numba.njit(cache=True, nogil=True)
def _explained(model_z, depth, valid, r, support, out):
    """out[y, x]: valid pixel (y, x) has a model depth within `support` of its own in the
    window of model_z (padded by r) about it."""
    h, w = valid.shape
    for y in range(h):
        for x in range(w):
            if not valid[y, x]:
                continue
            for dy in range(2 * r + 1):
                for dx in range(2 * r + 1):
                    if abs(model_z[y + dy, x + dx] - depth[y, x]) <= support:
                        out[y, x] = True
                        break
                if out[y, x]:
                    break


def _rigid(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) float32 R p + t, element-wise: a tall, thin matrix product runs multi-threaded in
    BLAS, several times slower on a busy machine."""
    x, y, z = (np.asarray(points[:, i], np.float32) for i in range(3))
    out = np.empty((len(x), 3), np.float32)
    for i in range(3):
        out[:, i] = x * np.float32(R[i, 0]) + y * np.float32(R[i, 1]) + z * np.float32(R[i, 2]) + np.float32(t[i])
    return out


def measure(points_world: np.ndarray, normals_world: np.ndarray, T_camera_to_world: np.ndarray,
            depth_m: np.ndarray, vertex_map: np.ndarray, valid: np.ndarray, intrinsics: Intrinsics,
            params: AlignmentParams = AlignmentParams()) -> Alignment:
    """Both fractions for world-frame model points and normals (N, 3) against one observation
    (camera-frame maps) seen from T_camera_to_world."""
    T = np.asarray(T_camera_to_world, np.float64)
    R, t = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
    p = _rigid(R, t, points_world)
    step = max(1, -(-len(p) // params.max_judged_points))
    n = _rigid(R, np.zeros(3), np.asarray(normals_world)[::step])     # only the judged share's
    judged, supported = model_support(p[::step], n, depth_m, vertex_map, valid, intrinsics, params)
    explained = explained_pixels(p, vertex_map, valid, intrinsics, params)
    judged_count, valid_count = int(judged.sum()), int(valid.sum())
    return Alignment(float(1.0 - supported.sum() / judged_count) if judged_count else 0.0,
                     float(1.0 - explained.sum() / valid_count) if valid_count else 0.0,
                     judged_count, valid_count)

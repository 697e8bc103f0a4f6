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
    them with depth support."""
    h, w = valid.shape
    row, col, inside = _project(points, intrinsics, (h, w), params.image_margin_px)
    facing = np.einsum("ij,ij->i", normals, points) < 0
    j = np.flatnonzero(inside & facing)
    row, col, p = row[j], col[j], points[j]
    observed = depth_m[row, col]
    occluded = (observed > 0) & (observed < p[:, 2] - params.occlusion_margin_m)
    supported = np.zeros(len(j), bool)
    r, max_d2 = params.window_px, params.support_m ** 2
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            y, x = np.clip(row + dy, 0, h - 1), np.clip(col + dx, 0, w - 1)
            d = vertex_map[y, x] - p
            supported |= valid[y, x] & (np.einsum("ij,ij->i", d, d) <= max_d2)
    judged = np.zeros(len(points), bool)
    judged[j[~occluded]] = True
    out = np.zeros(len(points), bool)
    out[j[~occluded & supported]] = True
    return judged, out


def explained_pixels(points: np.ndarray, vertex_map: np.ndarray, valid: np.ndarray, intrinsics: Intrinsics,
                     params: AlignmentParams = AlignmentParams()) -> np.ndarray:
    """(H, W) bool: valid depth pixels with a camera-frame model point (N, 3) projecting within
    the window at a depth within support_m of the pixel's (one point per pixel is kept: the
    last; a window pixel's lateral offset is a few millimetres, well inside the support)."""
    h, w = valid.shape
    row, col, inside = _project(points, intrinsics, (h, w), 0)
    r = params.window_px
    model_z = np.full((h + 2 * r, w + 2 * r), np.inf, np.float32)
    model_z[row[inside] + r, col[inside] + r] = points[inside, 2]
    depth = vertex_map[..., 2]
    explained = np.zeros((h, w), bool)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            explained |= np.abs(model_z[dy:dy + h, dx:dx + w] - depth) <= params.support_m
    return explained & valid


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
    p, n = _rigid(R, t, points_world), _rigid(R, np.zeros(3), normals_world)
    step = max(1, -(-len(p) // params.max_judged_points))
    judged, supported = model_support(p[::step], n[::step], depth_m, vertex_map, valid, intrinsics, params)
    explained = explained_pixels(p, vertex_map, valid, intrinsics, params)
    judged_count, valid_count = int(judged.sum()), int(valid.sum())
    return Alignment(float(1.0 - supported.sum() / judged_count) if judged_count else 0.0,
                     float(1.0 - explained.sum() / valid_count) if valid_count else 0.0,
                     judged_count, valid_count)

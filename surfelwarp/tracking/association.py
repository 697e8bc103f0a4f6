"""Projective association of warped model surfels with the depth maps (SurfelWarp Sec. VII-A):
each live surfel is paired with the depth pixel it projects to, gated by distance and normal angle.
The depth vertex and normal are moved to world once per solve (DepthTargets)."""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.dual_quaternion import _components
from surfelwarp.geometry.se3 import invert


@dataclass(frozen=True)
class DepthPairs:
    """Model surfels paired with depth pixels (the non-rigid data term's pairs)."""
    index: np.ndarray     # (C,) into the surfel arrays
    points: np.ndarray    # (C, 3) float64 depth vertices, world
    normals: np.ndarray   # (C, 3) float64 depth normals, world


class DepthTargets:
    """The valid depth pixels of one solve in world coordinates, as components (3, V), and each
    pixel's column among them (-1: invalid), so that association gathers 1-D arrays and
    transforms nothing per iteration."""

    def __init__(self, depth_vertex_map, depth_normal_map, depth_valid, intrinsics, T_camera_to_world):
        T_cw = np.asarray(T_camera_to_world, np.float64)
        self.T_wc = invert(T_cw)
        self.intrinsics = intrinsics
        self.shape = np.shape(depth_valid)
        valid = np.asarray(depth_valid, bool)
        # Each pixel's world vertex and normal side by side (V, 6): the compiled association
        # reads them at once (six rows apart, 4-8x slower, as the rows share cache sets).
        self.column = np.empty(valid.size, np.int64)
        self.packed = np.empty((int(np.count_nonzero(valid)), 6))
        _pack(np.asarray(depth_vertex_map), np.asarray(depth_normal_map), valid, np.ascontiguousarray(T_cw[:3, :3]),
              np.ascontiguousarray(T_cw[:3, 3]), self.column, self.packed)
        self.vertex, self.normal = self.packed[:, :3].T, self.packed[:, 3:].T


def pack_reference(depth_vertex_map, depth_normal_map, depth_valid, T_camera_to_world):
    """DepthTargets' (column, packed) in numpy passes (what the tests compare _pack with)."""
    T_cw = np.asarray(T_camera_to_world, np.float64)
    pixels = np.flatnonzero(np.asarray(depth_valid, bool))
    column = np.full(np.size(depth_valid), -1, np.int64)
    column[pixels] = np.arange(len(pixels))
    R, t = T_cw[:3, :3], T_cw[:3, 3]
    vertex = np.asarray(depth_vertex_map).reshape(-1, 3)[pixels].T.astype(np.float64)
    normal = np.asarray(depth_normal_map).reshape(-1, 3)[pixels].T.astype(np.float64)
    packed = np.empty((len(pixels), 6))
    packed[:, :3] = np.transpose(rigid_components(R, t, vertex))
    packed[:, 3:] = np.transpose(rigid_components(R, np.zeros(3), normal))
    return column, packed


@numba.njit(cache=True, nogil=True)
def _pack(vertex, normal, valid, R, t, column, packed):
    """pack_reference in one pass over the pixels, its products and sums in the same order (the
    same bits): on a 7-Scenes frame ~3.5 ms against ~58 ms for its gathers, casts and
    transposes."""
    h, w = valid.shape
    k = 0
    for y in range(h):
        for x in range(w):
            if not valid[y, x]:
                column[y * w + x] = -1
                continue
            column[y * w + x] = k
            v0, v1, v2 = np.float64(vertex[y, x, 0]), np.float64(vertex[y, x, 1]), np.float64(vertex[y, x, 2])
            n0, n1, n2 = np.float64(normal[y, x, 0]), np.float64(normal[y, x, 1]), np.float64(normal[y, x, 2])
            for i in range(3):
                packed[k, i] = v0 * R[i, 0] + v1 * R[i, 1] + v2 * R[i, 2] + t[i]
                packed[k, 3 + i] = n0 * R[i, 0] + n1 * R[i, 1] + n2 * R[i, 2] + 0.0
            k += 1


def rigid_components(R: np.ndarray, t: np.ndarray, p) -> list[np.ndarray]:
    """R p + t on components (3 arrays), element-wise: as a matrix product BLAS would run this
    tall, thin product multi-threaded, which is several times slower on a busy machine."""
    return [p[0] * R[i, 0] + p[1] * R[i, 1] + p[2] * R[i, 2] + t[i] for i in range(3)]


def associate_components(live, live_n, targets: DepthTargets, distance_gate_m: float,
                         min_normal_cos: float) -> DepthPairs:
    """associate() on world live surfels given as components (3, N): associate_reference's
    pairs in two compiled passes (its ~15 numpy passes took ~2.7 ms a call on 66k surfels, three
    calls a solve): each surfel's pixel, on numba's threads (each surfel alone), then the pairs
    gathered in surfel order (200k surfels: 17 ms on one thread, 8 in the two passes)."""
    intr = targets.intrinsics
    live, live_n = (np.ascontiguousarray(a, np.float64) for a in (live, live_n))
    n = live.shape[1]
    pick = np.empty(n, np.int64)
    _pick(live, live_n, targets.T_wc, np.array([intr.fx, intr.fy, intr.cx, intr.cy]), targets.shape[0],
          targets.shape[1], targets.column, targets.packed, distance_gate_m ** 2, min_normal_cos, pick)
    index, points, normals = np.empty(n, np.int64), np.empty((n, 3)), np.empty((n, 3))
    count = _gather(pick, targets.packed, index, points, normals)
    return DepthPairs(index[:count], points[:count], normals[:count])


def associate_reference(live, live_n, targets: DepthTargets, distance_gate_m: float,
                        min_normal_cos: float) -> DepthPairs:
    """associate_components in numpy passes (what the tests compare it with)."""
    intr = targets.intrinsics
    qx, qy, qz = rigid_components(targets.T_wc[:3, :3], targets.T_wc[:3, 3], live)
    h, w = targets.shape
    front = qz > 1e-6
    z = np.where(front, qz, 1.0)
    u = np.rint(intr.fx * qx / z + intr.cx)
    v = np.rint(intr.fy * qy / z + intr.cy)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    index = np.flatnonzero(inside)
    column = targets.column[v[index].astype(np.int64) * w + u[index].astype(np.int64)]
    ok = column >= 0
    index, column = index[ok], column[ok]
    dv, dn = np.take(targets.vertex, column, axis=1), np.take(targets.normal, column, axis=1)
    diff = np.take(live, index, axis=1) - dv
    keep = (np.einsum("ic,ic->c", diff, diff) < distance_gate_m ** 2) & \
           (np.einsum("ic,ic->c", np.take(live_n, index, axis=1), dn) > min_normal_cos)
    return DepthPairs(index[keep], dv[:, keep].T, dn[:, keep].T)    # C-ordered (C, 3): keep's axis comes first


@numba.njit(cache=True, nogil=True, parallel=True)
def _pick(live, live_n, T_wc, f, h, w, column, packed, max_d2, min_cos, pick):
    """pick[i]: the column of the depth pixel surfel i pairs with (-1: none), by the tests of
    associate_reference in its arithmetic's order."""
    for i in numba.prange(live.shape[1]):
        pick[i] = -1
        x, y, z = live[0, i], live[1, i], live[2, i]
        qx = x * T_wc[0, 0] + y * T_wc[0, 1] + z * T_wc[0, 2] + T_wc[0, 3]
        qy = x * T_wc[1, 0] + y * T_wc[1, 1] + z * T_wc[1, 2] + T_wc[1, 3]
        qz = x * T_wc[2, 0] + y * T_wc[2, 1] + z * T_wc[2, 2] + T_wc[2, 3]
        if not qz > 1e-6:
            continue
        u = np.rint(f[0] * qx / qz + f[2])
        v = np.rint(f[1] * qy / qz + f[3])
        if not (u >= 0 and u < w and v >= 0 and v < h):
            continue
        c = column[int(v) * w + int(u)]
        if c < 0:
            continue
        d0, d1, d2 = x - packed[c, 0], y - packed[c, 1], z - packed[c, 2]
        if not d0 * d0 + d1 * d1 + d2 * d2 < max_d2:
            continue
        if not live_n[0, i] * packed[c, 3] + live_n[1, i] * packed[c, 4] + live_n[2, i] * packed[c, 5] > min_cos:
            continue
        pick[i] = c


@numba.njit(cache=True, nogil=True)
def _gather(pick, packed, index, points, normals):
    """The picked pairs from the start of index, points and normals, in surfel order; their count."""
    count = 0
    for i in range(len(pick)):
        c = pick[i]
        if c < 0:
            continue
        index[count] = i
        for a in range(3):
            points[count, a] = packed[c, a]
            normals[count, a] = packed[c, 3 + a]
        count += 1
    return count


def associate(live_points: np.ndarray, live_normals: np.ndarray, depth_vertex_map: np.ndarray,
              depth_normal_map: np.ndarray, depth_valid: np.ndarray, intrinsics: Intrinsics,
              T_camera_to_world: np.ndarray, distance_gate_m: float = 0.03,
              min_normal_cos: float = 0.7) -> DepthPairs:
    """Projective association of world-frame live surfels with the camera-frame depth maps."""
    targets = DepthTargets(depth_vertex_map, depth_normal_map, depth_valid, intrinsics, T_camera_to_world)
    return associate_components(_components(live_points), _components(live_normals), targets, distance_gate_m, min_normal_cos)

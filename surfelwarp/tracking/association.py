"""Projective association of warped model surfels with the depth maps (SurfelWarp Sec. VII-A):
each live surfel is paired with the depth pixel it projects to, gated by distance and normal angle.
The depth vertex and normal are moved to world once per solve (DepthTargets)."""
from __future__ import annotations

from dataclasses import dataclass

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
        pixels = np.flatnonzero(np.asarray(depth_valid, bool))
        self.column = np.full(int(np.prod(self.shape)), -1, np.int64)
        self.column[pixels] = np.arange(len(pixels))
        R, t = T_cw[:3, :3], T_cw[:3, 3]
        vertex = np.asarray(depth_vertex_map).reshape(-1, 3)[pixels].T.astype(np.float64)
        normal = np.asarray(depth_normal_map).reshape(-1, 3)[pixels].T.astype(np.float64)
        self.vertex = np.array(rigid_components(R, t, vertex))
        self.normal = np.array(rigid_components(R, np.zeros(3), normal))


def rigid_components(R: np.ndarray, t: np.ndarray, p) -> list[np.ndarray]:
    """R p + t on components (3 arrays), element-wise: as a matrix product BLAS would run this
    tall, thin product multi-threaded, which is several times slower on a busy machine."""
    return [p[0] * R[i, 0] + p[1] * R[i, 1] + p[2] * R[i, 2] + t[i] for i in range(3)]


def associate_components(live, live_n, targets: DepthTargets, distance_gate_m: float,
                         min_normal_cos: float) -> DepthPairs:
    """associate() on world live surfels given as components (3, N)."""
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
    # np.take: several times faster than fancy indexing for gathers of 2-D arrays.
    dv, dn = np.take(targets.vertex, column, axis=1), np.take(targets.normal, column, axis=1)
    diff = np.take(live, index, axis=1) - dv
    keep = (np.einsum("ic,ic->c", diff, diff) < distance_gate_m ** 2) & \
           (np.einsum("ic,ic->c", np.take(live_n, index, axis=1), dn) > min_normal_cos)
    return DepthPairs(index[keep], dv[:, keep].T, dn[:, keep].T)    # (C, 3) views of (3, C) arrays


def associate(live_points: np.ndarray, live_normals: np.ndarray, depth_vertex_map: np.ndarray,
              depth_normal_map: np.ndarray, depth_valid: np.ndarray, intrinsics: Intrinsics,
              T_camera_to_world: np.ndarray, distance_gate_m: float = 0.03,
              min_normal_cos: float = 0.7) -> DepthPairs:
    """Projective association of world-frame live surfels with the camera-frame depth maps."""
    targets = DepthTargets(depth_vertex_map, depth_normal_map, depth_valid, intrinsics, T_camera_to_world)
    return associate_components(_components(live_points), _components(live_normals), targets, distance_gate_m, min_normal_cos)

"""Solver maps (SurfelWarp Sec. VII): surfels rendered as opaque disk splats at depth resolution.

Each pixel holds the index, camera-frame position and normal of the surfel whose disk the pixel's
ray meets first; the depth test uses the ray/disk intersection depth, so overlapping splats
resolve per pixel. Only the index is drawn (a compute shader's scatter, scatter.py): position
and normal are the surfel's own, gathered from the arrays that were drawn.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.base import FAR_M, NEAR_M, camera_points
from surfelwarp.render.scatter import Scatter

MAX_SIZE_PX = 255.0   # a disk is tried on at most this square of pixels about its centre
MIN_COS = 0.05        # grazing-ray clamp of |cos(ray, normal)| (about 87 degrees)
MAX_SIDE_PX = 32767   # the shader packs a pixel's column and row in 16 bits each


@dataclass(frozen=True)
class SolverMaps:
    """(H, W[, 3]) maps, row 0 = top image row. Empty pixels: index -1, zero vectors."""
    index: np.ndarray        # int32, index into the full surfel array
    vertex: np.ndarray       # float32, surfel centre, camera frame
    normal: np.ndarray       # float32, surfel normal
    intrinsics: Intrinsics


def _elements(indices: np.ndarray, n: int) -> np.ndarray:
    elements = np.asarray(indices).reshape(-1)
    if elements.dtype == bool:
        raise ValueError("indices must be integer indices, not a mask")
    if len(elements) and (elements.min() < 0 or elements.max() >= n):
        raise ValueError("indices out of range")
    return elements.astype(np.uint32)


def render_solver_maps(positions: np.ndarray, normals: np.ndarray, radii: np.ndarray,
                       intrinsics: Intrinsics, indices: np.ndarray | None = None,
                       near_m: float = NEAR_M, far_m: float = FAR_M,
                       fill_indices: np.ndarray | None = None, max_radius_px: float = 0.0) -> SolverMaps:
    """Render (N, 3) camera-frame surfels (normals, (N,) radii in metres) as opaque disks.

    `indices` selects the surfels drawn (e.g. the stable ones); maps still hold full-array indices.
    `fill_indices` are drawn only on the pixels the first set leaves empty.
    Disks reaching outside (near_m, far_m) in depth are dropped; a disk whose projection is wider
    than MAX_SIZE_PX is cut to that square about its centre. `max_radius_px` > 0 cuts each
    radius to that many pixels at the disk centre's depth (max_radius_px z / fx).
    """
    positions, normals = camera_points(intrinsics, positions, normals)
    radii = np.asarray(radii, np.float32).reshape(-1)
    n = len(positions)
    if len(radii) != n:
        raise ValueError("positions and radii differ in length")
    elements = np.arange(n, dtype=np.uint32) if indices is None else _elements(indices, n)
    fill = np.zeros(0, np.uint32) if fill_indices is None else _elements(fill_indices, n)
    intr = intrinsics
    if max(intr.width, intr.height) > MAX_SIDE_PX:
        raise ValueError(f"images of at most {MAX_SIDE_PX} pixels a side, not {intr.width}x{intr.height}")
    index = Scatter.of("surfel_splat.comp.glsl", {"positions": 0, "elements": 3, "normals": 4, "radii": 5},
                         scratch={6: 2}).run(
        len(elements) + len(fill), intr.height, intr.width,
        {"positions": positions, "normals": normals, "radii": radii, "elements": np.concatenate([elements, fill])},
        u_K=(intr.fx, intr.fy, intr.cx, intr.cy), u_size=(intr.width, intr.height), u_near_far=(near_m, far_m),
        u_max_size=MAX_SIZE_PX, u_max_radius_px=float(max_radius_px), u_min_cos=MIN_COS,
        u_count=len(elements) + len(fill), u_first_count=len(elements))
    vertex, normal = _gather(index, positions, normals)
    return SolverMaps(index=index, vertex=vertex, normal=normal, intrinsics=intrinsics)


@numba.njit(cache=True, nogil=True, parallel=True)
def _gather(index, positions, normals):
    """(H, W, 3) rows of positions and normals at a map's indices, zeros where it is empty
    (-1), in one pass (its image rows on numba's threads): numpy took a copy of each array with
    a zero row in front and two gathers (~4.4 ms a sheet frame)."""
    h, w = index.shape
    vertex, normal = np.zeros((h, w, 3), np.float32), np.zeros((h, w, 3), np.float32)
    for v in numba.prange(h):
        for u in range(w):
            i = index[v, u]
            if i >= 0:
                for c in range(3):
                    vertex[v, u, c] = positions[i, c]
                    normal[v, u, c] = normals[i, c]
    return vertex, normal


def drawn_rows(index: np.ndarray, positions: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) float32 maps of the rows of (N, 3) positions and normals that a map's `index`
    shows, zeros where it is empty: the solver maps in the frame those rows are in (world, from
    the live surfels drawn; they must be the arrays drawn, in the same order: the indices are
    not checked). maps_to_world would move the camera-frame maps back, at the cost of a
    rounding and 2.5-3.4 ms a 640x480 frame in `touch` runs; this gather takes 0.9-1.3."""
    return _gather(np.ascontiguousarray(index), np.ascontiguousarray(positions, np.float32),
                   np.ascontiguousarray(normals, np.float32))


def maps_to_world(maps: SolverMaps, T_camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solver maps in world coordinates, zero where no surfel was drawn (as rigid ICP expects)."""
    R = np.ascontiguousarray(T_camera_to_world[:3, :3].T, np.float32)
    # Whole maps (no masked gathers): the empty pixels' zeros turn into zeros. As (H*W, 3) rows,
    # one BLAS product a map: (H, W, 3) @ R made one per image row (both maps ~6 -> ~4 ms at
    # 640x480, the same bits).
    shape = maps.vertex.shape
    vertex = np.ascontiguousarray(maps.vertex, np.float32).reshape(-1, 3) @ R
    _shift_drawn(vertex, maps.index.reshape(-1), np.asarray(T_camera_to_world[:3, 3], np.float32))
    return vertex.reshape(shape), (np.ascontiguousarray(maps.normal, np.float32).reshape(-1, 3) @ R).reshape(shape)


@numba.njit(cache=True, nogil=True)
def _shift_drawn(vertex, index, t):
    """vertex[p] += t * hit[p], hit 1 where a surfel was drawn and 0 elsewhere: numpy's
    float32 operations in its order (an empty pixel gets t * 0, so its zero keeps numpy's sign)."""
    for p in range(len(index)):
        hit = np.float32(1.0) if index[p] >= 0 else np.float32(0.0)
        for i in range(3):
            vertex[p, i] += t[i] * hit

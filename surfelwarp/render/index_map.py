"""The fusion index map (SurfelWarp Sec. VI-A): surfels as unsized points on a supersampled grid.

Each surfel lands on at most one pixel (the one whose centre is nearest its projection); where
several land on the same pixel the closest to the camera wins. Pixels store only the surfel
index: a surfel's position, normal and confidence are gathers from the arrays that were drawn,
which travel with the map. Drawn by a compute shader's scatter (scatter.py), not as GL points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.base import FAR_M, NEAR_M, camera_points
from surfelwarp.render.scatter import Scatter


@dataclass(frozen=True)
class FusionMaps:
    """The index map (H*s, W*s), int32, row 0 the top image row, -1 where empty, and the
    surfels it indexes: camera-frame points and normals (N, 3) float32, confidences (N,)."""
    index: np.ndarray
    supersample: int
    intrinsics: Intrinsics       # of the supersampled grid
    points: np.ndarray
    normals: np.ndarray
    confidences: np.ndarray | None = None

    def _per_pixel(self, values: np.ndarray) -> np.ndarray:
        hit = self.index >= 0
        out = np.zeros(self.index.shape + values.shape[1:], values.dtype)
        out[hit] = values[self.index[hit]]
        return out

    @property
    def vertex(self) -> np.ndarray:
        """(H*s, W*s, 3) camera-frame position per pixel, zeros where empty."""
        return self._per_pixel(self.points)

    @property
    def normal(self) -> np.ndarray:
        return self._per_pixel(self.normals)

    @property
    def confidence(self) -> np.ndarray | None:
        return None if self.confidences is None else self._per_pixel(self.confidences)


def render_index_map(positions: np.ndarray, normals: np.ndarray, intrinsics: Intrinsics,
                     supersample: int = 1, confidence: np.ndarray | None = None,
                     near_m: float = NEAR_M, far_m: float = FAR_M) -> FusionMaps:
    """Render (N, 3) camera-frame surfels as points on the grid of `intrinsics.supersampled(s)`.

    Surfels with depth outside (near_m, far_m), behind the camera, or off the grid are dropped.
    """
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be a positive integer, not {supersample}")
    intr = intrinsics.supersampled(int(supersample))
    positions, normals = camera_points(intr, positions, normals)
    conf = (np.zeros(len(positions), np.float32) if confidence is None
            else np.asarray(confidence, np.float32).reshape(-1))
    if len(conf) != len(positions):
        raise ValueError("confidence and positions differ in length")
    index = Scatter.of("index_map.comp.glsl", {"positions": 0}).run(
        len(positions), intr.height, intr.width, {"positions": positions}, rows=_rows(positions, intr, near_m, far_m),
        u_K=(intr.fx, intr.fy, intr.cx, intr.cy),
        u_size=(intr.width, intr.height), u_near_far=(near_m, far_m), u_count=len(positions))
    return FusionMaps(index=index, supersample=int(supersample), intrinsics=intr, points=positions,
                      normals=normals, confidences=None if confidence is None else conf)


def _rows(positions: np.ndarray, intr: Intrinsics, near_m: float, far_m: float) -> tuple[int, int]:
    """(first, end) of the rows the points in (near_m, far_m) land on, a row more each side for
    the shader's float32 rounding: the scatter reads back and clears only those (a model on a
    third of the rows: render_index_map 8.4 -> 4.5 ms at 4x)."""
    z = positions[:, 2]
    ok = (z > near_m) & (z < far_m)
    t = positions[ok, 1] / z[ok]
    t = t[np.isfinite(t)]          # the shader drops NaN and infinite points too
    if len(t) == 0:
        return 0, 0
    v = np.clip(np.floor(intr.fy * np.array([t.min(), t.max()], np.float64) + intr.cy + 0.5), -2, intr.height + 2)
    return int(v.min()) - 1, int(v.max()) + 2

"""The surfel model: S_ref and S_live as parallel arrays (SurfelWarp Sec. III-IV).

S_ref[i] and S_live[i] share radius, confidence, time stamps, k-NN nodes and weights, colour.
Positions and normals are in world coordinates (the camera frame of the first frame):
`ref_*` before the warp, `live_*` after it.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numba
import numpy as np


@dataclass
class SurfelModel:
    ref_position: np.ndarray     # (N, 3) float32
    ref_normal: np.ndarray       # (N, 3) float32
    live_position: np.ndarray    # (N, 3) float32
    live_normal: np.ndarray      # (N, 3) float32
    radius: np.ndarray           # (N,) float32
    confidence: np.ndarray       # (N,) float32
    t_init: np.ndarray           # (N,) int32, frame counter at creation
    t_observed: np.ndarray       # (N,) int32, frame counter of the last fused observation
    knn: np.ndarray              # (N, k) int32 node indices
    weights: np.ndarray          # (N, k) float32 skinning weights (0 for unused slots)
    ids: np.ndarray              # (N,) uint32, unique for the surfel's whole life
    color: np.ndarray            # (N, 3) float32 RGB 0..255, fused like the geometry
    # (N,) float32 the confidence of the observations that had colour (== confidence when every
    # frame has it); 0: never seen in colour, so the next coloured observation sets the colour.
    color_weight: np.ndarray

    def __len__(self) -> int:
        return len(self.radius)

    def select(self, which: np.ndarray) -> "SurfelModel":
        """The surfels picked by a boolean mask or an index array, in that order."""
        rows = _rows(which)
        # np.take of rows is several times faster than boolean indexing of (N, c) arrays.
        return SurfelModel(**{f.name: np.take(getattr(self, f.name), rows, axis=0) for f in fields(self)})

    def concatenate(self, other: "SurfelModel") -> "SurfelModel":
        return SurfelModel(**{f.name: np.concatenate([getattr(self, f.name), getattr(other, f.name)])
                              for f in fields(self)})

    def select_then(self, which: np.ndarray, other: "SurfelModel") -> "SurfelModel":
        """select(which).concatenate(other) in one copy of the kept rows (a frame's removal
        and appending: two whole-model copies were ~12 ms on 270k surfels)."""
        rows = _rows(which)
        out = {}
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            a = out[f.name] = np.empty((len(rows) + len(theirs),) + mine.shape[1:], np.result_type(mine, theirs))
            _take_rows(mine, rows, a[:len(rows)])
            a[len(rows):] = theirs
        return SurfelModel(**out)

    @staticmethod
    def from_points(position, normal, radius, confidence, time: int, first_id: int, k: int = 4,
                    color=None) -> "SurfelModel":
        """New surfels whose reference and live geometry coincide; skinning is left empty.
        `color` (n, 3) RGB; without it the colour is 0 with weight 0."""
        n = len(position)
        position = np.ascontiguousarray(position, dtype=np.float32)
        normal = np.ascontiguousarray(normal, dtype=np.float32)
        confidence = np.asarray(confidence, np.float32)
        if color is None:
            color, color_weight = np.zeros((n, 3), np.float32), np.zeros(n, np.float32)
        else:
            color, color_weight = np.asarray(color, np.float32).reshape(n, 3), confidence.copy()
        return SurfelModel(position, normal, position.copy(), normal.copy(),
                           np.asarray(radius, np.float32), confidence,
                           np.full(n, time, np.int32), np.full(n, time, np.int32),
                           np.zeros((n, k), np.int32), np.zeros((n, k), np.float32),
                           np.arange(first_id, first_id + n, dtype=np.uint32), color, color_weight)


def _take_rows(a: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    """out[:] = a[rows] (rows along the first axis). Every model array has 4-byte items, copied
    as uint32 words in a compiled loop: np.take's per-row copy made a frame's removal 22 instead
    of 11 ms on 275k surfels (14 arrays)."""
    rows = np.asarray(rows, np.int64)
    if len(rows) and (rows.min() < 0 or rows.max() >= len(a)):
        raise IndexError(f"rows out of range for {len(a)} surfels")   # the kernel does not check
    if len(rows) and a.dtype.itemsize == 4 and a.dtype == out.dtype and a.flags.c_contiguous and out.flags.c_contiguous:
        _gather_words(a.reshape(len(a), -1).view(np.uint32), rows, out.reshape(len(out), -1).view(np.uint32))
    else:
        np.take(a, rows, axis=0, out=out)


@numba.njit(cache=True, nogil=True, parallel=True)
def _gather_words(src, rows, out):
    for i in numba.prange(len(rows)):         # each row alone, on numba's threads
        r = rows[i]
        for j in range(src.shape[1]):
            out[i, j] = src[r, j]


def _rows(which: np.ndarray) -> np.ndarray:
    """Row indices of a boolean mask or an index array, in that order."""
    which = np.asarray(which)
    return np.flatnonzero(which) if which.dtype == bool else which

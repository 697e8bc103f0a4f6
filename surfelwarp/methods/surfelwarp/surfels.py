"""The surfel model: S_ref and S_live as parallel arrays (SurfelWarp Sec. III-IV).

S_ref[i] and S_live[i] share radius, confidence, time stamps, k-NN nodes and weights.
Positions and normals are in world coordinates (the camera frame of the first frame):
`ref_*` before the warp, `live_*` after it.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

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

    def __len__(self) -> int:
        return len(self.radius)

    def select(self, which: np.ndarray) -> "SurfelModel":
        """The surfels picked by a boolean mask or an index array, in that order."""
        which = np.asarray(which)
        rows = np.flatnonzero(which) if which.dtype == bool else which
        # np.take of rows is several times faster than boolean indexing of (N, c) arrays.
        return SurfelModel(**{f.name: np.take(getattr(self, f.name), rows, axis=0) for f in fields(self)})

    def concatenate(self, other: "SurfelModel") -> "SurfelModel":
        return SurfelModel(**{f.name: np.concatenate([getattr(self, f.name), getattr(other, f.name)])
                              for f in fields(self)})

    @staticmethod
    def from_points(position, normal, radius, confidence, time: int, first_id: int, k: int = 4) -> "SurfelModel":
        """New surfels whose reference and live geometry coincide; skinning is left empty."""
        n = len(position)
        position = np.ascontiguousarray(position, dtype=np.float32)
        normal = np.ascontiguousarray(normal, dtype=np.float32)
        return SurfelModel(position, normal, position.copy(), normal.copy(),
                           np.asarray(radius, np.float32), np.asarray(confidence, np.float32),
                           np.full(n, time, np.int32), np.full(n, time, np.int32),
                           np.zeros((n, k), np.int32), np.zeros((n, k), np.float32),
                           np.arange(first_id, first_id + n, dtype=np.uint32))

"""The `observe` method: each frame's depth surfels are the live model; nothing is tracked.

A baseline for evaluation (good geometry, no correspondence over time) and the
simplest complete run of the CLI and its outputs.
"""
from __future__ import annotations

import numpy as np

from surfelwarp.io.outputs import FrameRecord
from surfelwarp.io.ply import vertex_table
from surfelwarp.preprocess import CameraObservation


class ObserveMethod:
    name = "observe"

    def __init__(self):
        self._next_id = 0
        self._table = None
        self.has_color: bool | None = None   # the first observation decides (PLYs keep one layout)

    def config(self) -> dict:
        return {}

    def process(self, obs: CameraObservation) -> FrameRecord:
        s = obs.surfels()
        n = len(s["position"])
        if self.has_color is None:
            self.has_color = obs.color is not None
        # A frame without colour, in a run with colour, writes 0 0 0 (as a surfel never seen in colour).
        color = s.get("color", np.zeros((n, 3), np.float32)) if self.has_color else None
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.uint32)
        self._next_id += n
        self._table = vertex_table(s["position"], s["normal"], s["position"], s["radius"], s["confidence"], ids,
                                   color)
        return FrameRecord(frame=obs.frame_index, reference_frame=obs.frame_index,
                           camera_to_world=np.eye(4), seconds={}, surfels=n)

    @property
    def started(self) -> bool:
        return self._table is not None

    def ahead(self, obs: CameraObservation) -> None:
        """Nothing to do before a frame."""

    def hold(self, obs: CameraObservation) -> FrameRecord:
        """The last frame's surfels stay the live model."""
        return FrameRecord(frame=obs.frame_index, reference_frame=obs.frame_index, camera_to_world=np.eye(4),
                           seconds={}, surfels=len(self._table), tracked=False)

    def live_vertices(self) -> tuple[np.ndarray, None]:
        return self._table, None

    def model_vertices(self) -> tuple[np.ndarray, None]:
        return self._table, None

    def model_bytes(self) -> int:
        return 0 if self._table is None else int(self._table.nbytes)

    def finish(self, out_dir, frames) -> None:
        """Nothing beyond the common outputs."""

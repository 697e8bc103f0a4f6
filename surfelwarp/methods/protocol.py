"""What the frame loop (run.py) and the comparison (report/) need of a reconstruction method."""
from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from surfelwarp.io.outputs import FrameRecord
from surfelwarp.preprocess import CameraObservation


@runtime_checkable
class Method(Protocol):
    name: str

    def config(self) -> dict:
        """Every parameter in force, for metrics.json."""

    @property
    def started(self) -> bool:
        """Whether there is a model (process() may not start one from a frame with too little depth)."""

    def process(self, obs: CameraObservation) -> FrameRecord:
        """One frame, top to bottom; the frame's record."""

    def ahead(self, obs: CameraObservation) -> None:
        """Work on an observation that reads no model, done before its frame: the run calls it
        on its read-ahead worker while the frame before is processed, with every observation in
        order. What it finds must be what process() would find (checked there, or found again)."""

    def hold(self, obs: CameraObservation) -> FrameRecord:
        """A frame with too little depth to track: the model and the pose are kept; its record."""

    def live_vertices(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The live model in this frame's camera: a PLY vertex table and faces (None: points)."""

    def model_vertices(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The reference model in the reference frame's camera, as live_vertices."""

    def model_bytes(self) -> int:
        """Memory the model holds (surfels or volume, mesh, warp field)."""

    def finish(self, out_dir: Path, frames: list[FrameRecord]) -> None:
        """End of a run: method-specific outputs (plots); may do nothing."""

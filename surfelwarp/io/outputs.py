"""The files a run writes (CONTRACT.md): live/frame-%06d.ply, model.ply, metrics.json.

Every file is written atomically, and metrics.json is rewritten after each saved frame, so a
run that stops early (bad frame, Ctrl-C) leaves complete, consistent files behind.
"""
from __future__ import annotations

import json
import resource
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from surfelwarp.io.ply import write_atomic, write_ply


@dataclass
class FrameRecord:
    """One processed frame, as metrics.json lists it."""
    frame: int
    reference_frame: int
    camera_to_world: np.ndarray
    seconds: dict[str, float]
    surfels: int = 0
    nodes: int = 0
    gauss_newton_iterations: int = 0
    energy: float = 0.0
    reinitialized: bool = False
    model_bytes: int = 0          # memory the model holds at the end of the frame
    # The method's own typed counts (dataclasses: the tracker's, fusion's, the volume's), listed
    # in metrics.json beside the common fields; fields that are None are left out.
    details: tuple = ()

    def to_json(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "details"}
        d["camera_to_world"] = np.asarray(self.camera_to_world, dtype=float).tolist()
        d["seconds"] = {k: round(float(v), 6) for k, v in self.seconds.items()}
        d["energy"] = float(self.energy)
        for part in self.details:
            d |= {k: v for k, v in asdict(part).items() if v is not None}
        return d

    def detail(self, kind: type):
        """The record's details of the given type (None: it has none)."""
        return next((part for part in self.details if isinstance(part, kind)), None)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # Linux reports KiB


class RunOutputs:
    def __init__(self, out_dir: Path, method: str, input_path: Path, config: dict):
        self.out_dir = Path(out_dir)
        self.method, self.input_path, self.config = method, str(input_path), config
        self.frames: list[FrameRecord] = []
        self.error: str | None = None

    def live_path(self, frame: int) -> Path:
        return self.out_dir / "live" / f"frame-{frame:06d}.ply"

    def save_live(self, frame: int, vertices: np.ndarray, faces: np.ndarray | None = None) -> None:
        write_ply(self.live_path(frame), vertices, faces)

    def remove_stale_live(self, frames: set[int]) -> None:
        """Drop live/frame-*.ply files of an earlier run into the same folder that this run
        will not rewrite, so that live/ and metrics.json describe one run."""
        for path in (self.out_dir / "live").glob("frame-*.ply"):
            stem = path.name[len("frame-"):-len(".ply")]
            if stem.isdigit() and int(stem) not in frames:
                path.unlink()

    def save_model(self, vertices: np.ndarray, faces: np.ndarray | None = None) -> None:
        write_ply(self.out_dir / "model.ply", vertices, faces)

    def add_frame(self, record: FrameRecord) -> None:
        self.frames.append(record)

    def summary(self) -> dict:
        totals = [r.seconds["total"] for r in self.frames]
        return {"frames": len(self.frames),
                "median_frame_seconds": float(np.median(totals)) if totals else 0.0,
                "peak_rss_mb": round(peak_rss_mb(), 1)}

    def write_metrics(self) -> Path:
        doc = {"method": self.method, "input": self.input_path, "config": self.config,
               "frames": [r.to_json() for r in self.frames], "summary": self.summary()}
        if self.error:
            doc["error"] = self.error
        path = self.out_dir / "metrics.json"
        write_atomic(path, (json.dumps(doc, indent=1) + "\n").encode())
        return path

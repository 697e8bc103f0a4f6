"""The files a run writes (CONTRACT.md): live/frame-%06d.ply, model.ply, metrics.json.

Every file is written atomically, and metrics.json is rewritten after each saved frame, so a
run that stops early (bad frame, Ctrl-C, kill, full disk) leaves complete, consistent files
behind. A run into a folder that holds an earlier run's outputs removes them only once its own
first frame is processed (`claim`), so a run that fails before that leaves the earlier one whole.
"""
from __future__ import annotations

import json
import math
import os
import resource
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import cv2
import numpy as np

from surfelwarp.errors import OutputError
from surfelwarp.io.ply import mesh_table, write_atomic, write_ply


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
    tracked: bool = True          # False: too little depth; the model and the pose were kept
    model_bytes: int = 0          # memory the model holds at the end of the frame
    rss_mb: float = 0.0           # the process's resident memory at the end of the frame
    # The seconds the frame's read-ahead work took by stage (read, preprocess, ahead), on the
    # worker while the frame before was processed; `seconds` holds only what the frame waited.
    ahead_seconds: dict[str, float] | None = None
    # The method's own typed counts (dataclasses: the tracker's, fusion's, the volume's), listed
    # in metrics.json beside the common fields; fields that are None are left out.
    details: tuple = ()

    def to_json(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "details"}
        d["camera_to_world"] = np.asarray(self.camera_to_world, dtype=float).tolist()
        d["seconds"] = {k: round(float(v), 6) for k, v in self.seconds.items()}
        if self.ahead_seconds is None:
            del d["ahead_seconds"]
        else:
            d["ahead_seconds"] = {k: round(float(v), 6) for k, v in self.ahead_seconds.items()}
        d["energy"] = float(self.energy)
        for part in self.details:
            d |= {k: v for k, v in asdict(part).items() if v is not None}
        return d

    def detail(self, kind: type):
        """The record's details of the given type (None: it has none)."""
        return next((part for part in self.details if isinstance(part, kind)), None)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # Linux reports KiB


def rss_mb() -> float:
    """Resident memory now (Linux: /proc/self/statm; elsewhere the peak)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return peak_rss_mb()
    return pages * resource.getpagesize() / 2**20


class RunOutputs:
    def __init__(self, out_dir: Path, method: str, input_path: Path, config: dict):
        self.out_dir = Path(out_dir)
        self.method, self.input_path, self.config = method, str(input_path), config
        self.frames: list[FrameRecord] = []
        self.skipped: list[int] = []      # frames with too little depth to start a model from
        self.missing: list[int] = []      # gaps in the input's frame numbers
        self.error: str | None = None

    def live_path(self, frame: int) -> Path:
        return self.out_dir / "live" / f"frame-{frame:06d}.ply"

    def save_live(self, frame: int, vertices: np.ndarray, faces: np.ndarray | None = None) -> None:
        write_ply(self.live_path(frame), vertices, faces)

    # An earlier run's outputs in OUT, with what `eval`, `mesh` and `view` made of them (other
    # files there are the user's and stay).
    EARLIER = ("live/frame-*.ply", "render/frame-*.png", "model.ply", "model_mesh.ply", "metrics.json",
               "eval.json", "surfels.png", "live.mp4", "checkpoint.pkl", "mesh/frame-*.ply", "view.html")

    def claim(self) -> None:
        """Remove an earlier run's outputs from OUT, so that it holds this run's alone."""
        try:
            for pattern in self.EARLIER:
                for path in self.out_dir.glob(pattern):
                    path.unlink()
        except OSError as exc:
            raise OutputError(self.out_dir, f"cannot remove an earlier run's outputs ({exc.strerror})") from None

    def remove_saved(self, frames: set[int]) -> None:
        """The live PLYs and renders of these frames."""
        for frame in frames:
            self.live_path(frame).unlink(missing_ok=True)
            self.render_path(frame).unlink(missing_ok=True)

    def render_path(self, frame: int) -> Path:
        return self.out_dir / "render" / f"frame-{frame:06d}.png"

    def save_render(self, frame: int, rgb: np.ndarray) -> None:
        ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
        if not ok:
            raise OutputError(self.render_path(frame), "cannot encode the render")
        write_atomic(self.render_path(frame), png.tobytes())

    def write_video(self, frames: list[int], fps: float = 10.0) -> Path | None:
        """OUT/live.mp4 of the renders of `frames` that exist, one video frame each (None: none)."""
        paths = [p for p in map(self.render_path, frames) if p.is_file()]
        if not paths:
            return None
        first = cv2.imread(str(paths[0]))
        path = self.out_dir / "live.mp4"
        tmp = path.with_name(f".live.tmp{os.getpid()}.mp4")
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, first.shape[1::-1])
        try:
            if not writer.isOpened():
                raise OutputError(path, "cannot write (OpenCV's video writer did not open)")
            for p in paths:
                image = cv2.imread(str(p))
                if image is None or image.shape != first.shape:
                    raise OutputError(p, "render cannot be read, or differs in size from the first")
                writer.write(image)
            writer.release()
            os.replace(tmp, path)
        except OSError as exc:
            raise OutputError(path, f"cannot write ({exc.strerror})") from None
        finally:
            writer.release()
            tmp.unlink(missing_ok=True)
        return path

    def save_mesh(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray,
                  color: np.ndarray | None = None) -> None:
        write_ply(self.out_dir / "model_mesh.ply", mesh_table(vertices, normals, color), faces)

    def save_model(self, vertices: np.ndarray, faces: np.ndarray | None = None) -> None:
        write_ply(self.out_dir / "model.ply", vertices, faces)

    def add_frame(self, record: FrameRecord) -> None:
        self.frames.append(record)

    def summary(self) -> dict:
        totals = [r.seconds["total"] for r in self.frames]
        return {"frames": len(self.frames),
                "median_frame_seconds": float(np.median(totals)) if totals else 0.0,
                "peak_rss_mb": round(peak_rss_mb(), 1),
                "skipped_frames": self.skipped,
                "untracked_frames": [r.frame for r in self.frames if not r.tracked],
                "missing_frames": self.missing}

    def write_metrics(self) -> Path:
        doc = {"method": self.method, "input": self.input_path, "config": self.config,
               "frames": [r.to_json() for r in self.frames], "summary": self.summary()}
        if self.error:
            doc["error"] = self.error
        path = self.out_dir / "metrics.json"
        write_atomic(path, (json.dumps(finite_or_null(doc), indent=1, allow_nan=False) + "\n").encode())
        return path


def finite_or_null(value):
    """`value` with every non-finite float (a rigid ICP that found no pairs: NaN) made None, so
    that metrics.json is strict JSON (null), which every parser reads."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v) for v in value]
    return value

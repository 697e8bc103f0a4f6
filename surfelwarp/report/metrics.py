"""Reading both runs' metrics.json and evaluating them: stage times, model sizes, speed."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from surfelwarp.errors import InputError
from surfelwarp.report.runner import METHODS


NO_GROUND_TRUTH = "no ground truth"


def load_metrics(run_dir: Path) -> dict:
    return json.loads((run_dir / "metrics.json").read_text())


def stage_seconds(metrics: dict, key: str = "seconds") -> tuple[list[int], dict[str, np.ndarray]]:
    """Frame numbers and per-stage seconds (0 where a frame lacks the stage), first-seen order;
    key="ahead_seconds": the work done on the read-ahead worker before each frame."""
    frames = [f["frame"] for f in metrics["frames"]]
    names: list[str] = []
    for f in metrics["frames"]:
        names += [k for k in f.get(key) or {} if k != "total" and k not in names]
    return frames, {k: np.array([(f.get(key) or {}).get(k, 0.0) for f in metrics["frames"]]) for k in names}


def model_counts(metrics: dict) -> dict[str, np.ndarray]:
    """Element counts over frames: surfels, voxels (all / observed) and mesh vertices, if reported."""
    out = {}
    for key in ("surfels", "voxels", "observed_voxels", "mesh_vertices"):
        values = [f.get(key) for f in metrics["frames"]]
        if any(v for v in values):
            out[key] = np.array([v or 0 for v in values], float)
    return out


def evaluate_runs(out: Path, seq_dir: Path) -> dict[str, dict] | None:
    """evaluate() of both runs, or None when the sequence has no ground truth."""
    from surfelwarp.data_tools.evaluate import evaluate
    results = {}
    for name in METHODS:
        try:
            results[name] = evaluate(out / name, seq_dir)
        except InputError as exc:
            if NO_GROUND_TRUTH in exc.problem:
                return None
            raise
    return results


INPUT_STAGES = ("read", "preprocess", "ahead")      # what a frame waited for of its read-ahead work


# Tracking: the shared rigid ICP, colour correspondences and Gauss-Newton, the nodes' last
# motion carried on, and each method's model maps and data points.
TRACKER_STAGES = ("motion", "solver_maps", "rigid", "predict", "features", "nonrigid")
# A saved frame's outputs (its live PLY and picture), inside its total but no model update.
OUTPUT_STAGES = ("write", "render")


def speed(metrics: dict[str, dict]) -> dict:
    """Median milliseconds per frame (frames after the first, which only initialises) of each
    method: total, input, shared tracker and model update (every other stage but a saved
    frame's outputs), and, given both methods, the ratios DynamicFusion / SurfelWarp of the
    median totals and model updates."""
    out = {}
    for name in (n for n in METHODS if n in metrics):
        frames = metrics[name]["frames"][1:] or metrics[name]["frames"]
        group = lambda f, names: sum(v for k, v in f["seconds"].items() if k in names)  # noqa: E731
        rows = {"total": [f["seconds"]["total"] for f in frames],
                "input": [group(f, INPUT_STAGES) for f in frames],
                "tracker": [group(f, TRACKER_STAGES) for f in frames],
                "model": [f["seconds"]["total"] - group(f, INPUT_STAGES + TRACKER_STAGES + OUTPUT_STAGES)
                          for f in frames]}
        out[name] = {k: 1000 * float(np.median(v)) for k, v in rows.items()}
    if len(out) < len(METHODS):
        return out
    sw, df = out["surfelwarp"], out["dynamicfusion"]
    out["ratio"] = df["total"] / sw["total"] if sw["total"] > 0 else float("nan")
    out["model_ratio"] = df["model"] / sw["model"] if sw["model"] > 0 else float("nan")
    # SurfelWarp can be no faster than its input + tracker, whatever its model update costs.
    out["ratio_bound"] = df["total"] / (sw["input"] + sw["tracker"]) if sw["input"] + sw["tracker"] > 0 else float("nan")
    return out
